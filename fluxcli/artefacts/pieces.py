"""Pieces several artefact kinds share: a surface and a sparse (CSR) matrix."""

from __future__ import annotations

import h5py
import numpy as np
import scipy.sparse as sp

from ..surface.mesh import Surface

# gzip for size, fletcher32 so that a corrupt chunk is detected when it is read
_PACKED = dict(compression="gzip", compression_opts=4, shuffle=True, fletcher32=True)


def write_surface(group: h5py.Group, surface: Surface) -> None:
    group.create_dataset("vertices", data=surface.vertices_mm).attrs["unit"] = "mm"
    group.create_dataset("faces", data=surface.faces)
    group.create_dataset("element_of_face", data=surface.element_of_face)
    group.create_dataset("areas", data=surface.element_areas_mm2).attrs["unit"] = "mm^2"
    group.attrs["n_elements"] = surface.n_elements
    group.attrs["sha256"] = surface.digest()
    if surface.element_ids is not None:
        group.create_dataset("element_ids", data=surface.element_ids)


def read_surface(group: h5py.Group) -> Surface:
    ids = group["element_ids"][()] if "element_ids" in group else None
    return Surface(group["vertices"][()], group["faces"][()], group["element_of_face"][()],
                   int(group.attrs["n_elements"]), ids)


def write_csr(group: h5py.Group, m: sp.csr_matrix) -> None:
    m = m.tocsr()
    group.create_dataset("data", data=m.data, **_PACKED)
    group.create_dataset("indices", data=m.indices.astype(np.int32), **_PACKED)
    group.create_dataset("indptr", data=m.indptr.astype(np.int64), **_PACKED)
    group.attrs["shape"] = np.asarray(m.shape, np.int64)


def read_csr(group: h5py.Group) -> sp.csr_matrix:
    shape = tuple(int(x) for x in group.attrs["shape"])
    return sp.csr_matrix((group["data"][()], group["indices"][()], group["indptr"][()]), shape=shape)
