"""The radiometric maps of a calibration.h5 (``/radiometric``), read back for reconstruct.

Written by ``fluxmap calibrate`` (:func:`fluxcli.artefacts.calibration.write_radiometric`);
read here without the artefact checks, since a calibration file made by other tools with
only that group is accepted.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np


def read_maps(path: Path, group: str, names: tuple[str, ...]) -> dict[str, np.ndarray | None] | None:
    """``{name: array or None}`` of ``<path>:/<group>``; None when the file has no such group.
    Raises OSError when ``path`` is not a readable HDF5 file."""
    from ..errors import UserError
    from .digest import unchanged

    with h5py.File(path, "r") as f:
        if unchanged(f) is False:  # written and sealed by fluxmap calibrate, edited since
            raise UserError(f"{path} was changed after 'fluxmap calibrate' wrote it (its results no longer match "
                            "the digest it recorded); calibrate again rather than edit it.")
        if group not in f:
            return None
        g = f[group]
        return {name: (g[name][()] if name in g else None) for name in names}
