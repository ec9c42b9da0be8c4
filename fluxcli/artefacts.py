"""Versioned HDF5 artefacts: provenance, atomic writes, and the content-addressed T cache.

Every artefact has root attributes ``fluxmap_version``, ``kind``, ``schema_version``,
``created``, ``config_sha256`` and ``inputs`` (JSON: name -> sha256 of input artefacts).
Files are written to a temporary name in the target folder and renamed into place, so a
crash never leaves a half-written artefact under the real name.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np
import scipy.sparse as sp

from . import __version__
from .errors import UserError
from .surface.mesh import Surface

SCHEMA_VERSIONS = {"transfer": 1, "transfer-index": 1, "simulation": 1, "reconstruction": 1, "tetmesh": 1}


@contextlib.contextmanager
def write_artefact(path: Path, kind: str, *, config_sha256: str = "", inputs: dict[str, str] | None = None) -> Iterator[h5py.File]:
    """Open a new HDF5 artefact for writing; it appears at ``path`` only when complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["fluxmap_version"] = __version__
            f.attrs["kind"] = kind
            f.attrs["schema_version"] = SCHEMA_VERSIONS[kind]
            f.attrs["created"] = created_utc()
            f.attrs["config_sha256"] = config_sha256
            f.attrs["inputs"] = json.dumps(inputs or {}, sort_keys=True)
            yield f
            if reproducible():
                _forget_durations(f)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def reproducible() -> _dt.datetime | None:
    """The time of ``SOURCE_DATE_EPOCH`` when set (the reproducible-builds convention), else None.

    Then every artefact records that time as ``created`` and no wall-clock durations
    (attributes named ``*seconds`` become NaN): the same inputs give the same bytes."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    return _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc) if epoch.isdigit() else None


def created_utc() -> str:
    """Now, or the ``SOURCE_DATE_EPOCH`` time (see :func:`reproducible`)."""
    return (reproducible() or _dt.datetime.now(_dt.timezone.utc)).isoformat(timespec="seconds")


def _forget_durations(group: h5py.Group) -> None:
    for name in list(group.attrs):
        if name.endswith("seconds") and np.ndim(group.attrs[name]) == 0:
            group.attrs[name] = np.nan
    for item in group.values():
        if isinstance(item, h5py.Group):
            _forget_durations(item)


def open_artefact(path: Path, kind: str) -> h5py.File:
    """Open an artefact for reading, refusing files of another kind or schema."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"artefact {path} does not exist; run the stage that makes it first.")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise UserError(f"artefact {path} is not a readable HDF5 file ({e}).") from None
    got_kind = f.attrs.get("kind")
    if got_kind != kind:
        f.close()
        raise UserError(f"artefact {path} is a {got_kind!r} artefact, not {kind!r}.")
    if int(f.attrs.get("schema_version", -1)) != SCHEMA_VERSIONS[kind]:
        v = f.attrs.get("schema_version")
        f.close()
        raise UserError(f"artefact {path} has schema version {v}; this fluxmap reads version "
                        f"{SCHEMA_VERSIONS[kind]} of {kind!r}. Rebuild it with --force.")
    return f


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ------------------------------------------------------------------ pieces
def write_surface(group: h5py.Group, surface: Surface) -> None:
    group.create_dataset("vertices", data=surface.vertices_mm).attrs["unit"] = "mm"
    group.create_dataset("faces", data=surface.faces)
    group.create_dataset("element_of_face", data=surface.element_of_face)
    group.create_dataset("areas", data=surface.element_areas_mm2).attrs["unit"] = "mm^2"
    group.attrs["n_elements"] = surface.n_elements
    if surface.element_ids is not None:
        group.create_dataset("element_ids", data=surface.element_ids)


def read_surface(group: h5py.Group) -> Surface:
    ids = group["element_ids"][()] if "element_ids" in group else None
    return Surface(group["vertices"][()], group["faces"][()], group["element_of_face"][()],
                   int(group.attrs["n_elements"]), ids)


def write_csr(group: h5py.Group, m: sp.csr_matrix) -> None:
    m = m.tocsr()
    group.create_dataset("data", data=m.data, compression="gzip", compression_opts=4, shuffle=True)
    group.create_dataset("indices", data=m.indices.astype(np.int32), compression="gzip", compression_opts=4, shuffle=True)
    group.create_dataset("indptr", data=m.indptr.astype(np.int64), compression="gzip", compression_opts=4)
    group.attrs["shape"] = np.asarray(m.shape, np.int64)


def read_csr(group: h5py.Group) -> sp.csr_matrix:
    shape = tuple(int(x) for x in group.attrs["shape"])
    return sp.csr_matrix((group["data"][()], group["indices"][()], group["indptr"][()]), shape=shape)


# ------------------------------------------------------------------ the T cache
def cache_key(parts: dict) -> str:
    """Content address: sha256 of the canonical JSON of everything T depends on."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def canonical(x):
    """Numbers rounded to 1 nm / 1e-9 so that float noise does not change a key."""
    if isinstance(x, dict):
        return {k: canonical(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [canonical(v) for v in np.asarray(x, dtype=object).tolist()] if isinstance(x, np.ndarray) else [canonical(v) for v in x]
    if isinstance(x, (float, np.floating)):
        r = round(float(x), 9)
        return 0.0 if r == 0 else r
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


# ------------------------------------------------------------------ staleness
def inputs_digest(**parts) -> str:
    """sha256 of what a stage's output depends on (config sections as dicts, digests)."""
    return cache_key(canonical({k: v for k, v in parts.items()}))


def is_up_to_date(path: Path, kind: str, digest: str) -> bool:
    """True when ``path`` is a readable ``kind`` artefact built from exactly ``digest``."""
    try:
        with h5py.File(path, "r") as f:
            return (f.attrs.get("kind") == kind and int(f.attrs.get("schema_version", -1)) == SCHEMA_VERSIONS[kind]
                    and f.attrs.get("inputs_digest") == digest)
    except (OSError, KeyError):
        return False
