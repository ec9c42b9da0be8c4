"""A digest of an artefact's results, recorded when it is written, so that a reader can
tell a file changed after the fact (``fluxmap study`` refuses one).

The file cannot hold the hash of its own bytes; it holds the sha256 of its provenance
attributes (config, geometry, input files) and of the datasets under the named groups
(their names, dtypes, shapes and bytes, in sorted order) as the root attribute
``results_sha256``, with the groups in ``results_sha256_groups``.
"""

from __future__ import annotations

import hashlib
import json

import h5py
import numpy as np

ATTR = "results_sha256"


PROVENANCE_ATTRS = ("config_json", "geometry_json", "input_files", "config_sha256")


def results_sha256(f: h5py.File, groups) -> str:
    h = hashlib.sha256()
    for a in PROVENANCE_ATTRS:  # what it was made from and for: a study compares set-ups by these
        h.update(f"{a}|{f.attrs.get(a, '')}|".encode())
    names: list[str] = []
    for g in groups:
        if g in f:
            f[g].visititems(lambda name, obj, g=g: names.append(f"{g}/{name}") if isinstance(obj, h5py.Dataset) else None)
    for name in sorted(names):
        a = f[name][()]
        if isinstance(a, (bytes, str)) or (isinstance(a, np.ndarray) and a.dtype == object):
            data = json.dumps(np.asarray(a, dtype=object).tolist(), default=lambda x: x.decode() if isinstance(x, bytes) else str(x)).encode()
        else:
            a = np.ascontiguousarray(a)
            data = a.tobytes()
        h.update(f"{name}|{getattr(a, 'dtype', 'str')}|{np.shape(a)}|".encode())
        h.update(data)
    return h.hexdigest()


def seal(f: h5py.File, groups) -> None:
    """Record the digest of ``groups`` (call last, when the results are written)."""
    f.attrs["results_sha256_groups"] = json.dumps(list(groups))
    f.attrs[ATTR] = results_sha256(f, groups)


def unchanged(f: h5py.File) -> bool | None:
    """True when the results still match the recorded digest, False when not, None when the
    file records none (made before digests were recorded)."""
    if ATTR not in f.attrs:
        return None
    groups = json.loads(f.attrs.get("results_sha256_groups", "[]"))
    return results_sha256(f, groups) == f.attrs[ATTR]
