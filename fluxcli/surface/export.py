"""The flux on the surface as a VTK XML PolyData file (``.vtp``) for ParaView and pyvista.

One cell per triangular face; per-element values are copied to every face of their
element (an element's value, not a share of it), so ``power_photons`` summed over faces
is *not* the total: sum it over ``element_id`` instead, or use the exitance, which is a
density. Faces that belong to no element (e.g. the unmeshed caps of a cylinder phantom)
get ``element_id = -1``, ``observed_state = -1`` and NaN values.

``observed_state``: 1 observed, 0 unobserved (no view sees the element: NaN, not zero),
-1 not an element. Units are in the array names and again, in words, in the field data
array ``units`` (one ``name: unit`` line per array).

VTK's string arrays hold ASCII only, so names and texts made from the user's words (a filter
"é-filter", a region "tête") are written in ASCII (:func:`ascii_name`: accents dropped, any other
character as its code point, e.g. ``u03bc`` for μ); a non-ASCII name once stopped reconstruct
after its artefact was written (exit 1).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

OBSERVED, UNOBSERVED, NOT_AN_ELEMENT = 1, 0, -1


def ascii_name(text: str) -> str:
    """``text`` in ASCII for VTK: accents dropped (é -> e), any other non-ASCII character as its
    code point (μ -> u03bc)."""
    import unicodedata

    out = []
    for ch in str(text):
        if ch.isascii():
            out.append(ch)
            continue
        base = "".join(c for c in unicodedata.normalize("NFKD", ch) if c.isascii())
        out.append(base if base else f"u{ord(ch):04x}")
    return "".join(out)


def element_to_face(values, element_of_face, fill=np.nan) -> np.ndarray:
    """Per-face array from a per-element array (faces of no element get ``fill``).

    Parameters
    ----------
    values : (n_elements, ...) array
    element_of_face : (F,) int array, element index or -1.
    """
    v = np.asarray(values)
    e = np.asarray(element_of_face, np.int64)
    out = np.full((len(e),) + v.shape[1:], fill, dtype=np.result_type(v.dtype, np.asarray(fill).dtype))
    m = e >= 0
    out[m] = v[e[m]]
    return out


def observed_state(observed, element_of_face) -> np.ndarray:
    """(F,) int8: 1 observed, 0 unobserved, -1 not an element."""
    st = np.where(np.asarray(observed, bool), OBSERVED, UNOBSERVED).astype(np.int8)
    return element_to_face(st, element_of_face, fill=np.int8(NOT_AN_ELEMENT)).astype(np.int8)


def polydata(vertices_mm, faces, element_of_face, element_arrays: dict, *, observed=None,
             units: dict | None = None, field: dict | None = None):
    """A pyvista PolyData of the surface with cell arrays mapped from elements.

    Parameters
    ----------
    vertices_mm : (V, 3) float, mm.
    faces : (F, 3) int, triangles.
    element_of_face : (F,) int, element index or -1.
    element_arrays : dict name -> (n_elements,) array
        Each becomes a cell array of that name (values of the face's element).
    observed : (n_elements,) bool, optional
        Adds ``observed_state`` (see module docstring).
    units : dict name -> unit text, optional
        Written as the field-data string array ``units``.
    field : dict name -> scalar or string, optional
        Extra field data (e.g. ``exposure_s``).
    """
    import pyvista as pv

    f = np.asarray(faces, np.int64)
    mesh = pv.PolyData(np.asarray(vertices_mm, float), np.hstack([np.full((len(f), 1), 3), f]).ravel())
    eof = np.asarray(element_of_face, np.int64)
    mesh.cell_data["element_id"] = eof
    if observed is not None:
        mesh.cell_data["observed_state"] = observed_state(observed, eof)
    written = {}  # the name given -> the ASCII name written (distinct: a clash keeps the code points)
    for name, values in element_arrays.items():
        v = np.asarray(values)
        fill = np.nan if v.dtype.kind == "f" else -1
        out = ascii_name(name)
        if out in written.values() or out in ("element_id", "observed_state"):
            out = "".join(c if c.isascii() else f"u{ord(c):04x}" for c in str(name))
        written[name] = out
        mesh.cell_data[out] = element_to_face(v, eof, fill=fill)
    names = ["element_id"] + (["observed_state"] if observed is not None else []) + list(element_arrays)
    unit_text = {"element_id": "index of the flux element (-1: not an element)",
                 "observed_state": "1 observed, 0 unobserved, -1 not an element"} | dict(units or {})
    mesh.field_data["units"] = np.array([ascii_name(f"{written.get(n, n)}: {unit_text.get(n, 'dimensionless')}")
                                         for n in names])
    mesh.field_data["coordinates_unit"] = np.array(["mm"])
    for k, v in (field or {}).items():
        v = np.atleast_1d(np.asarray(v))
        mesh.field_data[ascii_name(k)] = np.array([ascii_name(x) for x in v]) if v.dtype.kind in "US" else v
    return mesh


def write_vtp(path, mesh) -> Path:
    """Write a PolyData as VTK XML (binary, zlib) atomically: complete or absent."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".vtp", dir=path.parent)
    os.close(fd)
    try:
        mesh.save(tmp, binary=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
