"""Progress that moves: per batch of rays, across worker processes."""

from __future__ import annotations

import numpy as np

from fluxcli.optics.camera import ThinLensCamera
from fluxcli.optics.transfer import LensSampling, build_transfer, views_for
from fluxcli.progress import run_tasks
from fluxcli.surface import phantoms


def _halves(x, progress=None):
    for f in (0.25, 0.5, 0.75):
        progress(f)
    return x * 2


def test_run_tasks_returns_results_in_order_serially_and_in_workers():
    args = [(k,) for k in range(5)]
    assert run_tasks(_halves, args, label="t", jobs=1, quiet=True) == [0, 2, 4, 6, 8]
    assert run_tasks(_halves, args, label="t", jobs=2, quiet=True) == [0, 2, 4, 6, 8]


def test_build_transfer_reports_every_batch_up_to_one():
    cam = ThinLensCamera.from_pose(lens_center_mm=(0, 0, 300.0), look=(0, 0, -1), up=(0, 1, 0), focal_length_mm=25.0,
                                   aperture_radius_mm=3.0, focus_distance_mm=300.0, nx=24, ny=24, pixel_pitch_mm=0.2)
    surf = phantoms.sphere(radius_mm=8.0, n_latitude=6, n_longitude=8)[0]
    seen = []
    build_transfer(surf, views_for(cam, []), estimator="lens", lens_sampling=LensSampling(lens_samples_min=64),
                   rays_per_batch=2000, progress=seen.append)
    assert len(seen) > 5  # many batches, not one call per view
    assert np.all(np.diff(seen) >= 0) and seen[-1] == 1.0 and 0 < seen[0] < 1
