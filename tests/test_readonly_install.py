"""fluxmap imports and runs for a user who can write neither the install folder nor a home.

numba's ``cache=True`` used to raise ``RuntimeError: cannot cache function '_cut': no locator
available`` at import in that case (shared lab installs, read-only containers,
``setpriv --reuid=65534``).  These tests run the kernels' modules as user 65534 ("nobody"),
with HOME pointing nowhere, through the system's Python 3 on this venv's packages (the venv's
own interpreter may sit under a home that user cannot enter).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SYSTEM_PYTHON = Path("/usr/bin/python3")
KERNEL_MODULES = ("fluxcli.optics.visibility", "fluxcli.optics.transfer_kernel", "fluxcli.optics.embree_native")


def _system_python_matches() -> bool:
    if not SYSTEM_PYTHON.exists():
        return False
    out = subprocess.run([str(SYSTEM_PYTHON), "-c", "import sys; print(sys.version_info[:2])"],
                         capture_output=True, text=True)
    return out.stdout.strip() == str(tuple(sys.version_info[:2]))


needs_nobody = pytest.mark.skipif(
    not (hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("setpriv") and _system_python_matches()),
    reason="needs root, setpriv and a system python3 of this interpreter's version, to run as user 65534")


@pytest.fixture
def open_dir():
    """A folder user 65534 can enter and write (pytest's tmp_path sits under root's 0700 folder)."""
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="fluxmap-nobody-", dir="/tmp"))
    d.chmod(0o777)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _as_nobody(code: str, tmp_path: Path, *, tmpdir: Path) -> subprocess.CompletedProcess:
    site = sysconfig.get_paths()["purelib"]
    env = {"PATH": "/usr/bin:/bin", "HOME": "/nonexistent", "TMPDIR": str(tmpdir),
           "PYTHONPATH": os.pathsep.join([str(ROOT), site]), "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                           str(SYSTEM_PYTHON), "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)


@needs_nobody
def test_kernels_import_with_a_temporary_cache(open_dir):
    tmp_path = open_dir
    code = ("import fluxcli, importlib\n"
            f"for m in {KERNEL_MODULES!r}: importlib.import_module(m)\n"
            "import os; print(fluxcli.NUMBA_CACHE, os.environ.get('NUMBA_CACHE_DIR'))\n")
    out = _as_nobody(code, tmp_path, tmpdir=tmp_path)
    assert out.returncode == 0, out.stderr
    where, folder = out.stdout.split()
    assert where == "temporary"
    assert Path(folder).parent == tmp_path  # the private cache sits under TMPDIR


def test_kernels_compile_uncached_when_nothing_is_writable(tmp_path):
    """No folder at all can be written (a read-only root with no writable /tmp): caching is
    switched off with one notice, and cache=True kernels still compile and run.  Run in a fresh
    interpreter whose writability probe says no to every folder (nothing here can make /tmp
    read-only for real)."""
    (tmp_path / "kern.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    code = ("import os, sys\n"
            "os.environ.pop('NUMBA_CACHE_DIR', None)\n"
            "import fluxcli._numba_cache as c\n"
            "c._writable = lambda folder: False\n"
            "where = c.configure()\n"
            f"sys.path.insert(0, {str(tmp_path)!r})\n"
            "import importlib\n"
            f"for m in {KERNEL_MODULES!r}: importlib.import_module(m)\n"
            "import numpy as np, kern\n"
            "print(where, kern.twice(np.arange(3)).sum())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["off", "6"]
    assert "no writable folder for numba's kernel cache" in out.stderr
    assert not list(tmp_path.glob("**/*.nbi"))  # nothing was cached


@needs_nobody
def test_fluxmap_simulate_runs_as_a_user_who_can_write_neither_install_nor_home(open_dir):
    """The issue's case itself: `setpriv --reuid=65534 fluxmap simulate` with HOME pointing nowhere,
    the install folder (this checkout) not writable by that user: the stage runs to its artefact,
    its kernels cached in a private folder under TMPDIR, and nothing is written into the install."""
    from tiny_pipeline import tiny_config

    assert not (ROOT / "fluxcli").stat().st_mode & 0o002 and (ROOT / "fluxcli").stat().st_uid != 65534
    before = {p for p in (ROOT / "fluxcli").rglob("*")}
    cfg = tiny_config(open_dir)
    (open_dir / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    code = "import sys\nfrom fluxcli.cli import main\nsys.argv = ['fluxmap', 'simulate', 'cfg.yaml', '-q']\nmain()\n"
    out = _as_nobody(code, open_dir, tmpdir=open_dir)
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr and "cannot cache" not in out.stderr
    assert (open_dir / "run" / "simulation.h5").is_file()
    assert list((open_dir / "fluxmap-numba-cache-65534").rglob("*.nbi"))  # the private cache took the kernels
    assert {p for p in (ROOT / "fluxcli").rglob("*")} == before  # nothing written into the install
