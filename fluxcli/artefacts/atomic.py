"""The one atomic writer: every file fluxmap writes appears complete under its name or not at all.

A file is written to a temporary name in its target folder (``.NAME.HOST.PID.RANDOM.tmp``),
flushed to disk (fsync), renamed over the target, and the folder is fsynced so that the
rename survives a power cut.  Files are created with mode 0666 minus the umask (0644 by
default), so colleagues can read results and share a T cache.  A temporary file whose
writing process no longer runs (a killed run) is removed the next time anything is
written to that folder (only this machine's: another machine sharing the folder may still
be writing its own).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import socket
from pathlib import Path
from typing import Iterator

_TMP = re.compile(r"^\..+\.([A-Za-z0-9-]+)\.(\d+)\.[0-9a-f]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def host_tag() -> str:
    """This machine's name as it appears in temporary names (a shared T cache on a network
    file system must not lose another machine's file in progress)."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:40] or "host"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def clean_stale_temps(folder: Path) -> list[Path]:
    """Remove temporary files of writers that no longer run; returns what was removed."""
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = _TMP.match(name)
        if m and m.group(1) == host_tag() and not _alive(int(m.group(2))):
            p = Path(folder) / name
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


def temp_name(path: Path) -> Path:
    """A temporary name beside ``path`` that says which process writes it (same suffix,
    so libraries that pick a format by suffix still do)."""
    return path.with_name(f".{path.name}.{host_tag()}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}")


def fsync_path(path: Path, *, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems cannot fsync a directory
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path to write; on success it is fsynced and renamed to ``path``.

    The temporary file already exists (empty, mode 0666 & ~umask) when the body starts;
    on any exception (including KeyboardInterrupt) it is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_temps(path.parent)
    tmp = temp_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    os.close(fd)
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent, directory=True)
    finally:
        if tmp.exists():
            with contextlib.suppress(OSError):
                tmp.unlink()


def write_text(path: Path | str, text: str) -> None:
    """Write a text file atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def write_bytes(path: Path | str, data: bytes) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)
