"""Versioned HDF5 artefacts: provenance, atomic writes, checked reads.

Every artefact has root attributes ``fluxmap_version``, ``kind``, ``schema_version``,
``created``, ``config_sha256``, ``inputs`` (JSON, what the stage names as its inputs),
and the provenance that lets a later stage check it was made for the same set-up:

- ``config_json``: the resolved config (every default filled in), JSON;
- ``geometry_json`` / ``geometry_sha256``: the placed geometry it was made for (system:
  camera, lens, sensor, mirrors, stage; subject: surface, poses; and the digest of the
  surface as built);
- ``input_files``: JSON ``{name: {"path": ..., "sha256": ...}}`` of the input artefacts
  and image files it was made from.

Files are written through :func:`fluxcli.artefacts.atomic.atomic_path`.  Reading goes
through :func:`open_artefact`, which refuses another kind or schema and names a missing
or corrupt dataset together with the command that remakes the file.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from .. import __version__
from ..errors import UserError
from .atomic import atomic_path
from .digest import unchanged
from .kinds import KINDS, SCHEMA_VERSIONS


# ------------------------------------------------------------------ provenance
@dataclass
class Provenance:
    """How an artefact was made: resolved config, geometry and input files."""

    config: dict[str, Any] = field(default_factory=dict)
    geometry: dict[str, Any] = field(default_factory=dict)
    input_files: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def geometry_sha256(self) -> str:
        return cache_key(canonical(self.geometry)) if self.geometry else ""

    def add_file(self, name: str, path: Path, base: Path | None = None) -> None:
        """Record an input artefact or image file by name, path (relative to ``base`` when
        given, so the artefact does not depend on where the project lives) and digest."""
        self.input_files[name] = {"path": portable_path(path, base), "sha256": file_sha256(path)}


def read_provenance(f: h5py.File) -> Provenance:
    def load(name):
        try:
            return json.loads(f.attrs.get(name, "{}") or "{}")
        except (TypeError, ValueError):
            return {}

    return Provenance(load("config_json"), load("geometry_json"), load("input_files"))


def _flatten(x: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(x, dict):
        out: dict[str, Any] = {}
        for k, v in x.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out or {prefix: {}}
    return {prefix: x}


def _show(v: Any) -> str:
    if isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v):
        return f"sha256 {v[:12]}..."  # a digest: its start says enough
    if v is None:
        return "not set"
    if isinstance(v, float) and v == int(v) and abs(v) < 1e15:
        return f"{v:g}"
    if isinstance(v, list):
        if not v:
            return "none"
        if any(isinstance(x, (dict, list)) for x in v):
            return f"{len(v)} item(s)" if v else "none"
        return "[" + ", ".join(_show(x) for x in v) + "]"
    return str(v)


# Set-up keys added after artefacts were first made, with the value that means what an artefact
# made without the key meant: absent and this value are the same set-up (an artefact made
# before the key existed is not refused for it).
ADDED_KEYS = {"subject.refine_faces": 0}


def _comparable(geometry: dict) -> dict:
    flat = _flatten(canonical(geometry))
    return {k: v for k, v in flat.items() if not (k in ADDED_KEYS and v == ADDED_KEYS[k])}


def geometry_differences(stored: dict, now: dict, name: str = "the artefact") -> list[str]:
    """Dotted keys whose values differ: ``"key: OLD in NAME, NEW now"`` pieces."""
    a, b = _comparable(stored), _comparable(now)
    out = []
    for k in sorted(set(a) | set(b)):
        if a.get(k) != b.get(k):
            out.append((k, a.get(k), b.get(k)))
    label = {"surface_sha256": "the subject surface as built"}
    return [f"{label.get(k, k)}: {_show(x)} in {name}, {_show(y)} now" for k, x, y in out]


def check_geometry(path: Path, stored: Provenance, now_geometry: dict, *, remedy: str) -> None:
    """Refuse an artefact made for another geometry, naming each key that differs."""
    if not stored.geometry:
        raise UserError(f"{path} records no geometry (made by an older fluxmap), so it cannot be checked "
                        f"against this config; {remedy}.")
    if _comparable(stored.geometry) == _comparable(now_geometry):
        return
    diffs = geometry_differences(stored.geometry, now_geometry, Path(path).name)
    shown = "; ".join(diffs[:6]) + (f" (and {len(diffs) - 6} more)" if len(diffs) > 6 else "")
    raise UserError(f"{path} was made for another set-up than this config describes: {shown}. {remedy}.")


# ------------------------------------------------------------------ writing
def recorded_seconds(seconds: float) -> float:
    """A run time to store in an artefact: NaN under SOURCE_DATE_EPOCH (a reproducible run
    records no wall-clock times, so two runs give the same bytes)."""
    return float("nan") if os.environ.get("SOURCE_DATE_EPOCH") else float(seconds)


def portable_path(path, base=None) -> str:
    """``path`` relative to ``base`` (a folder) when given, so that artefacts made in two
    clones of the project are byte-identical; readers resolve it against the same base."""
    if base is None:
        return str(path)
    return os.path.relpath(Path(path).resolve(), Path(base).resolve())

@contextlib.contextmanager
def write_artefact(path: Path, kind: str, *, config_sha256: str = "", inputs: dict[str, str] | None = None,
                   provenance: Provenance | None = None) -> Iterator[h5py.File]:
    """Open a new HDF5 artefact for writing; it appears at ``path`` only when complete."""
    with atomic_path(path) as tmp:
        # no chunk cache: each chunk goes to the file when its dataset is written, so the layout
        # (and the bytes) do not depend on when Python happens to close a dataset object
        with h5py.File(tmp, "w", rdcc_nbytes=0) as f:
            f.attrs["fluxmap_version"] = __version__
            f.attrs["kind"] = kind
            f.attrs["schema_version"] = SCHEMA_VERSIONS[kind]
            f.attrs["created"] = created_utc()
            f.attrs["config_sha256"] = config_sha256
            p = provenance or Provenance()
            # the names and hashes of input artefacts and image files, beside what the stage names
            f.attrs["inputs"] = json.dumps(dict(inputs or {}) | {n: d["sha256"] for n, d in p.input_files.items()},
                                           sort_keys=True)
            f.attrs["config_json"] = json.dumps(p.config, sort_keys=True)
            f.attrs["geometry_json"] = json.dumps(canonical(p.geometry), sort_keys=True)
            f.attrs["geometry_sha256"] = p.geometry_sha256
            f.attrs["input_files"] = json.dumps(p.input_files, sort_keys=True)
            yield f
            if reproducible():
                _forget_durations(f)


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


def put(group: h5py.Group, name: str, data, **kwargs) -> h5py.Dataset:
    """Create dataset ``name`` (relative to ``group``) with the unit its kind declares."""
    ds = group.create_dataset(name, data=data, **kwargs)
    kind = KINDS.get(str(group.file.attrs.get("kind", "")))
    spec = kind.dataset(ds.name.lstrip("/")) if kind is not None else None
    if spec is not None:
        if spec.unit:
            ds.attrs["unit"] = spec.unit
        if spec.meaning:
            ds.attrs["meaning"] = spec.meaning
    return ds


# ------------------------------------------------------------------ reading
class _Missing:
    """What an artefact's groups, datasets and attributes share: a name the file lacks is a
    UserError naming the file, the dataset (or attribute) and the command that remakes it."""

    _fx_file: "ArtefactFile"

    def _fx_wrap(self, obj):
        kind = _CheckedGroup if isinstance(obj, h5py.Group) else _CheckedDataset if isinstance(obj, h5py.Dataset) else None
        if kind is None:
            return obj
        out = kind(obj.id)
        out._fx_file = self._fx_file
        return out

    def __getitem__(self, name):
        if isinstance(name, str):
            self._fx_file._fx_last = name
        try:
            return self._fx_wrap(super().__getitem__(name))
        except KeyError:
            if isinstance(name, str) and not isinstance(self, h5py.Dataset):
                where = name if self.name in ("/", None) else f"{self.name.strip('/')}/{name}"
                raise UserError(f"artefact {self._fx_file._fx_path} is incomplete: it has no dataset '{where}'; "
                                f"{self._fx_file._remedy()}.") from None
            raise

    def get(self, name, default=None, getclass=False, getlink=False):
        if getclass or getlink or name in self:
            return super().get(name, default, getclass, getlink)
        return default

    @property
    def attrs(self):
        a = _CheckedAttrs(self)
        a._fx_file, a._fx_owner = self._fx_file, self.name
        return a


class _CheckedAttrs(h5py.AttributeManager):
    def get(self, name, default=None):
        return super().__getitem__(name) if name in self else default

    def __getitem__(self, name):
        try:
            return super().__getitem__(name)
        except KeyError:
            on = "" if self._fx_owner in ("/", None) else f" of '{self._fx_owner.strip('/')}'"
            raise UserError(f"artefact {self._fx_file._fx_path} is incomplete: it has no attribute '{name}'{on}; "
                            f"{self._fx_file._remedy()}.") from None


class _CheckedGroup(_Missing, h5py.Group):
    pass


class _CheckedDataset(_Missing, h5py.Dataset):
    pass


class ArtefactFile(_Missing, h5py.File):
    """An artefact open for reading: a missing or unreadable dataset (or attribute), at any
    depth, becomes a UserError naming the file, the dataset and the command that remakes it."""

    def _setup(self, path: Path, kind: str) -> "ArtefactFile":
        self._fx_path, self._fx_kind, self._fx_last, self._fx_file = Path(path), kind, None, self
        return self

    def _remedy(self) -> str:
        k = KINDS.get(self._fx_kind)
        return (f"delete it and run '{k.made_by}' again (or use --force)" if k is not None
                else "delete it and make it again")

    def __exit__(self, exc_type, exc, tb):
        super().__exit__(exc_type, exc, tb)
        if exc_type is not None and issubclass(exc_type, OSError) and not isinstance(exc, UserError):
            where = f" (reading '{self._fx_last}')" if self._fx_last else ""
            raise UserError(f"artefact {self._fx_path} is corrupt{where}: {exc}; {self._remedy()}.") from None
        return False


_SEALS_HELD: set[tuple] = set()  # (path, inode, size, mtime) of files whose seal was checked in this process


def _seal_holds(path: Path, f: h5py.File) -> bool:
    """The file's results still match its recorded digest (or it records none); each file is
    hashed once per process while it is unchanged on disk (a report opens it several times)."""
    st = path.stat()
    key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
    if key in _SEALS_HELD:
        return True
    if unchanged(f) is False:
        return False
    _SEALS_HELD.add(key)
    return True


def _text(v) -> str:
    """An attribute as text for a message (bytes decoded, numpy scalars as plain numbers)."""
    if isinstance(v, bytes):
        return v.decode(errors="replace")
    return str(v.item()) if hasattr(v, "item") and getattr(v, "ndim", 1) == 0 else str(v)


def _version(v) -> int | None:
    """A schema_version attribute as an int, or None where it is none (missing, text, a float)."""
    try:
        return int(v) if v is not None and float(v) == int(v) else None
    except (TypeError, ValueError, OverflowError):
        return None


def open_artefact(path: Path, kind: str, *, check: bool = True) -> ArtefactFile:
    """Open an artefact for reading, refusing files of another kind or schema, or incomplete ones."""
    path = Path(path)
    if not path.is_file():
        what = KINDS.get(kind)
        hint = f"run '{what.made_by}' first" if what is not None else "run the stage that makes it first"
        raise UserError(f"artefact {path} does not exist; {hint}.")
    try:
        f = ArtefactFile(path, "r")._setup(path, kind)
    except OSError as e:
        raise UserError(f"artefact {path} is not a readable HDF5 file ({e}); delete it and make it again.") from None
    got_kind = f.attrs.get("kind")
    if got_kind != kind:
        f.close()
        if got_kind is None:
            raise UserError(f"artefact {path} is an HDF5 file but no fluxmap artefact (it has no 'kind' attribute); "
                            f"give a {kind}.h5 that fluxmap made.")
        raise UserError(f"artefact {path} is a {_text(got_kind)!r} artefact, not {kind!r}.")
    if _version(f.attrs.get("schema_version")) != SCHEMA_VERSIONS[kind]:  # (another tool's text: no version)
        v = _text(f.attrs.get("schema_version"))
        remedy = f._remedy()
        f.close()
        raise UserError(f"artefact {path} has schema version {v}; this fluxmap reads version "
                        f"{SCHEMA_VERSIONS[kind]} of {kind!r}; {remedy}.")
    spec = KINDS.get(kind)
    if check and spec is not None:
        missing = [d for d in spec.required if d not in f]
        if missing:
            remedy = f._remedy()
            f.close()
            raise UserError(f"artefact {path} is incomplete: it has no dataset '{missing[0]}'"
                            + (f" (nor {len(missing) - 1} other(s))" if len(missing) > 1 else "") + f"; {remedy}.")
    if check and not _seal_holds(path, f):  # sealed when written (reconstruction.h5), and edited since
        made_by = spec.made_by if spec is not None else "the stage that made it"
        f.close()
        raise UserError(f"artefact {path} was changed after it was written: its results no longer match the digest "
                        f"{made_by} recorded when it made it. Refusing it; make it again with '{made_by}'.")
    return f


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ------------------------------------------------------------------ content addresses
def cache_key(parts: dict) -> str:
    """Content address: sha256 of the canonical JSON of everything T depends on."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def canonical(x):
    """Numbers rounded to 1 nm / 1e-9 so that float noise does not change a key."""
    if isinstance(x, dict):
        return {str(k): canonical(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [canonical(v) for v in x.tolist()]
    if isinstance(x, (list, tuple)):
        return [canonical(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (float, np.floating)):
        r = round(float(x), 9)
        return 0.0 if r == 0 else r
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def inputs_digest(**parts) -> str:
    """sha256 of what a stage's output depends on (config sections as dicts, digests)."""
    return cache_key(canonical({k: v for k, v in parts.items()}))


def is_up_to_date(path: Path, kind: str, digest: str) -> bool:
    """True when ``path`` is a readable ``kind`` artefact built from exactly ``digest``."""
    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("kind") == kind and _version(f.attrs.get("schema_version")) == SCHEMA_VERSIONS[kind]
                        and f.attrs.get("inputs_digest") == digest)
    except (OSError, KeyError):
        return False
