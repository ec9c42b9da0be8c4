"""``fluxmap info ARTEFACT``: what an artefact holds and how it was made, as text."""

from __future__ import annotations

import json
from pathlib import Path

import h5py

from ..errors import UserError
from .digest import unchanged
from .kinds import KINDS, SCHEMA_VERSIONS
from .store import _show, canonical, read_provenance

_SET_UP_KEYS = ("system.camera.pixels", "system.camera.pixel_pitch_mm", "system.camera.lens.focal_length_mm",
                "system.camera.lens.f_number", "system.camera.lens.aperture_diameter_mm",
                "system.camera.lens.focus_distance_mm", "system.camera.pose.lens_center_mm",
                "subject.poses.heights_mm", "subject.poses.rotations_deg")


def _get(d: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def describe(path: Path | str) -> str:
    """A multi-line description of the artefact at ``path``; UserError if it is not one."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"info: {path} is a folder; give an artefact file (e.g. {path / 'simulation.h5'}).")
    if not path.is_file():
        raise UserError(f"info: {path} does not exist.")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise UserError(f"info: {path} is not an HDF5 artefact ({e}).") from None
    with f:
        kind = str(f.attrs.get("kind", ""))
        if not kind:
            raise UserError(f"info: {path} is an HDF5 file but not a fluxmap artefact (no 'kind' attribute).")
        spec = KINDS.get(kind)
        lines = [f"{path}: {kind} artefact" + (f" ({spec.description})" if spec else ""),
                 f"  schema version {f.attrs.get('schema_version')} (this fluxmap reads "
                 f"{SCHEMA_VERSIONS.get(kind, '?')}), made by fluxmap {f.attrs.get('fluxmap_version')} "
                 f"on {f.attrs.get('created')}" + (f" with '{spec.made_by}'" if spec else "")]
        prov = read_provenance(f)
        if f.attrs.get("config_sha256"):
            lines.append(f"  config sha256 {f.attrs['config_sha256']}")
        if prov.geometry:
            lines.append(f"  geometry sha256 {f.attrs.get('geometry_sha256', '')}")
            for key in _SET_UP_KEYS:
                v = _get(prov.geometry, key)
                if v is not None:
                    lines.append(f"    {key}: {_show(canonical(v))}")
            surf = _get(prov.geometry, "subject.surface")
            if isinstance(surf, dict):
                lines.append(f"    subject.surface: {json.dumps(surf)}")
            mirrors = _get(prov.geometry, "system.mirrors")
            if mirrors:
                lines.append(f"    system.mirrors: {len(mirrors)}")
        else:
            lines.append("  no geometry recorded (made by an older fluxmap)")
        sealed = unchanged(f)
        if sealed is not None:
            lines.append("  seal: its results match the digest recorded when it was written" if sealed else
                         "  SEAL BROKEN: its results were changed after it was written (readers refuse it)")
        if prov.input_files:
            lines.append("  made from:")
            for name, d in sorted(prov.input_files.items()):
                lines.append(f"    {name}: {d.get('path')} (sha256 {str(d.get('sha256'))[:16]}...)")
        lines.append("  holds:")

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                unit = obj.attrs.get("unit", "")
                if not unit and spec is not None and spec.dataset(name) is not None:
                    unit = spec.dataset(name).unit
                lines.append(f"    {name}  {obj.shape} {obj.dtype}" + (f"  [{unit}]" if unit else ""))

        f.visititems(visit)
        if spec is not None:
            missing = [d for d in spec.required if d not in f]
            if missing:
                lines.append(f"  INCOMPLETE: missing {', '.join(missing)}; remake it with '{spec.made_by}'")
    return "\n".join(lines)
