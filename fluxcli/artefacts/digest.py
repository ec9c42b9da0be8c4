"""A digest of an artefact's results, recorded when it is written, so that a reader can
tell a file changed after the fact (``fluxmap study`` refuses one).

The file cannot hold the hash of its own bytes; it holds the sha256 of its provenance
attributes (config, geometry, input files) and of the datasets under the named groups
(their names, dtypes, shapes and bytes, in sorted order) as the root attribute
``results_sha256``, with the groups in ``results_sha256_groups``.

Version 2 (``results_sha256_version``) also hashes every root attribute and the attributes
of every group and dataset under the named groups: a region's names, the exposure that
turns its photons into photons/s and a filter's transmission live in attributes, and
version 1 let them be edited unseen.  A file without the version attribute was sealed by
version 1 and is checked by it.
"""

from __future__ import annotations

import hashlib
import json

import h5py
import numpy as np

ATTR = "results_sha256"
VERSION = 2
_OWN = (ATTR, "results_sha256_groups", "results_sha256_version")


PROVENANCE_ATTRS = ("config_json", "geometry_json", "input_files", "config_sha256")


def _attrs_bytes(obj) -> bytes:
    """An object's attributes (but the digest's own), sorted by name, as bytes."""
    items = [(k, obj.attrs[k]) for k in sorted(obj.attrs) if k not in _OWN]
    return json.dumps([[k, np.asarray(v).tolist()] for k, v in items],
                      default=lambda x: x.decode() if isinstance(x, bytes) else str(x)).encode()


def results_sha256(f: h5py.File, groups, version: int = VERSION) -> str:
    h = hashlib.sha256()
    for a in PROVENANCE_ATTRS:  # what it was made from and for: a study compares set-ups by these
        h.update(f"{a}|{f.attrs.get(a, '')}|".encode())
    names: list[str] = []  # datasets
    holders = ["/"]  # groups (and named types): their attributes count from version 2
    for g in groups:
        if g not in f:
            continue
        if isinstance(f[g], h5py.Dataset):
            names.append(g)
            continue
        holders.append(g)
        f[g].visititems(lambda name, obj, g=g: (names if isinstance(obj, h5py.Dataset) else holders).append(f"{g}/{name}"))
    if version >= 2:
        for name in sorted(holders):
            h.update(f"{name}|".encode() + _attrs_bytes(f[name]))
    for name in sorted(names):
        a = f[name][()]
        if isinstance(a, (bytes, str)) or (isinstance(a, np.ndarray) and a.dtype == object):
            data = json.dumps(np.asarray(a, dtype=object).tolist(), default=lambda x: x.decode() if isinstance(x, bytes) else str(x)).encode()
        else:
            a = np.ascontiguousarray(a)
            data = a.tobytes()
        h.update(f"{name}|{getattr(a, 'dtype', 'str')}|{np.shape(a)}|".encode())
        h.update(data)
        if version >= 2:
            h.update(_attrs_bytes(f[name]))
    return h.hexdigest()


def seal(f: h5py.File, groups) -> None:
    """Record the digest of ``groups`` (call last, when the results are written)."""
    f.attrs["results_sha256_groups"] = json.dumps(list(groups))
    f.attrs["results_sha256_version"] = VERSION
    f.attrs[ATTR] = results_sha256(f, groups)


def unchanged(f: h5py.File) -> bool | None:
    """True when the results still match the recorded digest, False when not, None when the
    file records none (made before digests were recorded)."""
    if ATTR not in f.attrs:
        return None
    try:
        groups = json.loads(f.attrs.get("results_sha256_groups", "[]"))
        version = int(f.attrs.get("results_sha256_version", 1))
    except (ValueError, TypeError):
        return False  # the digest's own record was edited
    if not isinstance(groups, list) or not all(isinstance(g, str) for g in groups):
        return False
    try:
        return results_sha256(f, groups, version) == f.attrs[ATTR]
    except (KeyError, OSError, TypeError, ValueError):  # a link to nowhere, a dataset that cannot be read
        return False
