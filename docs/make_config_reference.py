"""Write docs/config-reference.md from the config schema (run: make config-reference).

One row per key: its dotted path (``[]`` marks a list item, ``{key}`` a mapping's value),
the type, the default, the unit (from the key's name, the project's convention) and the
description the schema carries.  ``tests/test_docs.py`` fails when the file is out of
date, so a schema change comes with the regenerated reference.
"""

from __future__ import annotations

import re
import sys
import types
import typing
from pathlib import Path

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "config-reference.md"

# name suffix -> unit (longest first wins)
UNIT_SUFFIXES = [
    ("_photons_per_mm2", "photons mm⁻² per exposure"), ("_e_per_pixel", "electrons per pixel"),
    ("_e_per_s", "electrons s⁻¹"), ("_mm_s", "mm s⁻¹"), ("_per_mm", "mm⁻¹"), ("_mm2", "mm²"), ("_mm", "mm"), ("_deg", "degrees"),
    ("_nm", "nm"), ("_s", "s"), ("_photons", "photons"), ("_counts", "ADC counts"), ("_e", "electrons"),
    ("electrons_per_count", "electrons per count"),
]


def unit_of(name: str) -> str:
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix) or name == suffix:
            return unit
    return ""


def _type_name(t) -> str:
    origin = typing.get_origin(t)
    args = typing.get_args(t)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in args)
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in args)
    if origin in (tuple,):
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return "[" + ", ".join(_type_name(a) for a in args) + "]"
    if origin in (dict,):
        return f"mapping {_type_name(args[0])} → {_type_name(args[1])}"
    if t is type(None):
        return "null"
    if isinstance(t, type) and issubclass(t, BaseModel):
        return "section"
    return getattr(t, "__name__", str(t)).replace("PosixPath", "path").replace("Path", "path")


def _models_in(t) -> list[tuple[str, type]]:
    """(path suffix, model) for every config section reachable from a field's type."""
    origin = typing.get_origin(t)
    args = typing.get_args(t)
    if origin is typing.Annotated:
        return _models_in(args[0])
    if origin in (typing.Union, types.UnionType):
        return [m for a in args for m in _models_in(a)]
    if origin is tuple:
        inner = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        return [("[]" + s, m) for s, m in _models_in(inner)] if inner is not None else []
    if origin is dict:
        return [("{" + _type_name(args[0]) + "}" + s, m) for s, m in _models_in(args[1])]
    if isinstance(t, type) and issubclass(t, BaseModel):
        return [("", t)]
    return []


def _default(field) -> str:
    if field.is_required():
        return "required"
    d = field.default
    if d is PydanticUndefined:
        return ""
    if isinstance(d, BaseModel):
        return "(section defaults)"
    if d is None:
        return "none"
    if isinstance(d, tuple):
        d = list(d)
    return f"`{d}`"


def _variant(model: type) -> str:
    """A union member's tag, e.g. ``phantom: cylinder`` (what selects it)."""
    for name, f in model.model_fields.items():
        if typing.get_origin(f.annotation) is typing.Literal and f.is_required():
            return f"{name}: {typing.get_args(f.annotation)[0]}"
    return model.__name__


def rows(model: type, prefix: str = "", seen: tuple = ()) -> list[list[str]]:
    out = []
    for name, f in model.model_fields.items():
        key = f.alias or name
        path = f"{prefix}{key}"
        models = _models_in(f.annotation)
        desc = (f.description or "").replace("|", "\\|").replace("\n", " ")
        variants = len({m for _, m in models}) > 1
        if typing.get_origin(f.annotation) is typing.Literal and f.is_required() and len(typing.get_args(f.annotation)) == 1:
            desc = desc or "Selects this variant."
        kind = "one of the variants below" if variants else _type_name(f.annotation)
        out.append([f"`{path}`", kind + (" \\| null" if variants and not f.is_required() else ""), _default(f),
                    unit_of(key), desc])
        for suffix, m in models:
            if m in seen:
                continue
            sub = f"{path}{suffix}."
            if variants:
                out.append([f"`{path}{suffix}`", f"*{_variant(m)}*", "", "", (m.__doc__ or "").strip().split("\n")[0]])
            out += rows(m, sub, seen + (m,))
    return out


def render() -> str:
    sys.path.insert(0, str(ROOT))
    from fluxcli.config import Config

    head = ("# Config reference\n\n"
            "Generated from the schema in `fluxcli/config.py` by `docs/make_config_reference.py` "
            "(`make config-reference`); do not edit by hand. Paths in a config are relative to the config "
            "file; unknown keys are errors; units are in the key names (the unit column spells them out); "
            "angles in degrees; the world frame is in mm, right-handed, z up. Where a section has variants "
            "(a phantom, a flux), the rows in *italics* name the key that selects one, and the rows below "
            "it are that variant's keys.\n\n")
    table = ["| key | type | default | unit | description |", "|---|---|---|---|---|"]
    table += ["| " + " | ".join(r) + " |" for r in rows(Config)]
    return head + "\n".join(table) + "\n"


if __name__ == "__main__":
    text = render()
    if "--check" in sys.argv:
        sys.exit(0 if OUT.is_file() and OUT.read_text() == text else 1)
    OUT.write_text(text)
    print(f"wrote {OUT} ({text.count(chr(10)) - 2} lines)")
