"""Where numba keeps the compiled kernels (``@njit(cache=True)``), for users who cannot write it.

numba caches next to the source (``__pycache__``) or in the user's cache folder; when neither
is writable -- a shared lab install, a read-only container, a service account with no home --
it refuses to compile a cached function and fluxmap crashed on import.  Here, once, before any
kernel module is imported: if neither place is writable, point numba at a private folder under
the temporary directory; if not even that is writable, compile without caching (every run then
compiles its kernels again, which costs time, not correctness) and say so once.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
        return True
    except OSError:
        return False


def _user_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "numba"


def configure() -> str:
    """Make sure numba has somewhere to cache; return which: 'user', 'in-tree', 'user-wide',
    'temporary' or 'off'."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return "user"
    if _writable(_PACKAGE / "optics" / "__pycache__"):
        return "in-tree"
    if _writable(_user_cache()):
        return "user-wide"
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    folder = Path(tempfile.gettempdir()) / f"fluxmap-numba-cache-{uid}"
    if _writable(folder):
        os.environ["NUMBA_CACHE_DIR"] = str(folder)
        if "numba" in sys.modules:  # imported before fluxcli: its config was read already
            from numba.core import config

            config.CACHE_DIR = str(folder)
        return "temporary"
    from numba.core.dispatcher import Dispatcher

    Dispatcher.enable_caching = lambda self: None  # no writable folder at all: compile every run
    sys.stderr.write("fluxmap: notice: no writable folder for numba's kernel cache "
                     f"({_PACKAGE}, {_user_cache()}, {tempfile.gettempdir()}); kernels are compiled "
                     "afresh each run (set NUMBA_CACHE_DIR to a writable folder to keep them)\n")
    return "off"


KERNEL = "transfer_kernel.lens_columns"  # the ray-casting kernel every T build runs first


def kernels_compiled() -> bool:
    """Whether numba's cache already holds the ray-casting kernels (so that a T build will not
    spend its first minute compiling them): the kernel's index file in the folder
    :func:`configure` chose."""
    folders = [Path(os.environ["NUMBA_CACHE_DIR"])] if os.environ.get("NUMBA_CACHE_DIR") else []
    folders += [_PACKAGE / "optics" / "__pycache__", _user_cache()]
    for folder in folders:
        try:
            if folder.is_dir() and next(folder.rglob(f"{KERNEL}-*.nbi"), None) is not None:
                return True
        except OSError:
            continue
    return False


COMPILING = ("compiling the ray-casting kernels (numba, once after an install: about 20 s of one core; "
             "later runs reuse them)")
