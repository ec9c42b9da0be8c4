"""Before any compute: the folders a stage writes in can be written, and the memory it will
need is there.  Each refusal is a :class:`~fluxcli.errors.UserError` naming the config keys
to change.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import UserError


def check_writable(folder: Path, key: str) -> None:
    """Make sure ``folder`` exists (creating it) and a file can be written in it; the
    message names the config key that chose it."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UserError(f"{key}: {folder} is a file, not a folder; choose another path.") from None
    except OSError as e:
        raise UserError(f"{key}: cannot create the folder {folder} ({e.strerror or e}); "
                        "choose a path you can write to.") from None
    if not folder.is_dir():
        raise UserError(f"{key}: {folder} is not a folder; choose another path.")
    probe = folder / f".fluxmap-write-test.{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UserError(f"{key}: cannot write in {folder} ({e.strerror or e}); choose a folder you can "
                        "write to, or fix its permissions.") from None


def check_folders(workdir: Path, cache_dir: Path | None = None, cache_key: str = "workdir") -> None:
    """The workdir (and the T cache ``cache_dir``, chosen by config key ``cache_key``) must be
    writable before a stage computes anything; temporary files killed runs left are removed."""
    from .artefacts.atomic import clean_stale_temps

    check_writable(workdir, "workdir")
    clean_stale_temps(workdir)
    if cache_dir is not None:
        check_writable(cache_dir, cache_key)


def available_memory_bytes() -> int:
    """Memory the OS says can be allocated now (MemAvailable), else the physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def _gb(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e8 else f"{n / 1e6:.3g} MB"


def check_memory(need_bytes: float, what: str, keys: str) -> None:
    """Refuse work whose estimated memory exceeds what is available, naming the keys to change."""
    avail = available_memory_bytes()
    if need_bytes > 0.8 * avail:
        raise UserError(f"{what} would need about {_gb(need_bytes)} of memory; {_gb(avail)} is available. "
                        f"Reduce {keys}.")
