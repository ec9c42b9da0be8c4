"""reconstruction.h5 through its container (fluxcli.artefacts.reconstruction): the schema in
artefacts/kinds.py declares every dataset the writer lays out, and the readers give back what
the solves put in."""

from __future__ import annotations

import h5py
import numpy as np

from tiny_pipeline import tiny_run  # noqa: F401  (session fixture)


def _datasets(path):
    out = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.append(name) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_every_dataset_written_is_declared_in_the_kind(tiny_run):
    from fluxcli.artefacts.kinds import KINDS

    d, _, _ = tiny_run
    declared = {x.name for x in KINDS["reconstruction"].datasets}
    written = _datasets(d / "run" / "reconstruction.h5")
    assert "flux/power" in written and "per_pose/headline_total" in written
    undeclared = [n for n in written if n not in declared and not any(n.startswith(g + "/") for g in declared)]
    assert undeclared == [], undeclared


def test_readers_give_back_the_written_results(tiny_run):
    from fluxcli.artefacts import reconstruction as RA

    d, _, _ = tiny_run
    path = d / "run" / "reconstruction.h5"
    s, m = RA.read_summary(path), RA.read_maps(path)
    with h5py.File(path, "r") as f:
        power, observed = f["flux/power"][()], f["flux/observed"][()].astype(bool)
        per_pose = f["per_pose/total"][()]
        truth = f["truth/power"][()]
    assert observed.any()
    np.testing.assert_array_equal(m.observed, observed)
    np.testing.assert_array_equal(np.isnan(m.power), ~observed)
    np.testing.assert_array_equal(m.power[observed], power[observed])
    np.testing.assert_array_equal(s.totals, per_pose)
    np.testing.assert_array_equal(s.truth, truth)
    assert len(s.heights_mm) == 2 and s.joint_over_poses  # two heights, solved jointly
    # the joint total over observed elements is /flux's power summed: the written total, not recomputed apart
    assert np.isclose(np.nansum(s.power), np.nansum(np.where(observed, power, 0.0)))
    assert m.surface.n_elements == power.size
