"""Speed ratios of the T builder, each measured within this one run (machines are noisy).

Run: make bench   (or .venv/bin/python benchmarks/bench_transfer.py)

1. lens vs pairwise estimator at matched accuracy (<= 1 % L1 against a refined lens T)
   on a defocused patch;
2. one pose of paper-3d (65 536 pixels x 1600 elements, three views): seconds, rays/s;
3. build-T on the demo's poses with --jobs 2 vs --jobs 1;
4. a cache hit vs a build.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fluxcli.config import load_config  # noqa: E402
from fluxcli.optics.camera import ThinLensCamera  # noqa: E402
from fluxcli.optics.transfer import LensSampling, PairwiseSampling, build_transfer, views_for  # noqa: E402
from fluxcli.stages import build_t  # noqa: E402
from fluxcli.stages.context import RunContext  # noqa: E402
from fluxcli.surface import phantoms  # noqa: E402


def timed(fn, *a, **kw):
    t = time.perf_counter()
    out = fn(*a, **kw)
    return time.perf_counter() - t, out


def estimators() -> None:
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=5, focus_distance_mm=100, nx=48, ny=48, pixel_pitch_mm=0.05)
    subject = phantoms.patch(size_mm=(1.5, 1.5), n=(2, 2), center_mm=[0.3, 0.1, -110.0], normal=[0.2, 0, 1])[0]
    views = views_for(cam, [])
    ref = build_transfer(subject, views, lens_sampling=LensSampling(surface_samples_per_pixel=8, lens_samples_min=2048,
                                                                    lens_samples_max=8192)).T.toarray()

    def err(T):
        return np.abs(T.toarray() - ref).sum() / ref.sum()

    t_lens, res = timed(build_transfer, subject, views)
    e_lens = err(res.T)
    for k in (4, 6, 8, 10, 12, 14, 16):
        t_pw, res = timed(build_transfer, subject, views, estimator="pairwise",
                          pairwise_sampling=PairwiseSampling(surface_subdivisions=2 * k, pixel_subdivisions=k))
        e_pw = err(res.T)
        if e_pw <= max(e_lens, 0.01):
            break
    print(f"[1] defocused patch: lens {t_lens:.3f} s (L1 error {e_lens:.2%}), pairwise {t_pw:.3f} s "
          f"(L1 error {e_pw:.2%}, {2 * k}x surface, {k}x pixel): pairwise/lens time ratio {t_pw / t_lens:.1f}")


def paper3d_pose(tmp: Path) -> None:
    cfg = load_config(ROOT / "configs" / "paper-3d.yaml",
                      ["subject.poses.rotations_deg=[0]", f"transfer.cache_dir={tmp / 'p3d'}"])
    views, placer, todo = build_t.plan(cfg)
    scene = todo[0][0]
    t, res = timed(build_transfer, scene.surface, views, scene.occluders)
    rays = sum(s["rays"] for s in res.stats.values())
    eff = build_t.summarise(res, scene)["efficiency"]
    print(f"[2] paper-3d one pose: {t:.1f} s, nnz {res.T.nnz}, {rays / 1e6:.1f} M rays cast "
          f"({rays / t / 1e6:.2f} M rays/s including sampling), efficiency "
          + ", ".join(f"{k} {v:.3e}" for k, v in eff.items()))


def jobs_and_cache(tmp: Path) -> None:
    def run(jobs, force):
        cfg = load_config(ROOT / "configs" / "demo.yaml", [f"transfer.cache_dir={tmp / 'demo'}", f"workdir={tmp / 'w'}"])
        return timed(build_t.run, cfg, RunContext(quiet=True, jobs=jobs, force=force))[0]

    t1 = run(1, True)
    t2 = run(2, True)
    hit = run(1, False)
    print(f"[3] demo build-T (4 poses): --jobs 1 {t1:.2f} s, --jobs 2 {t2:.2f} s: speed-up {t1 / t2:.2f}x")
    print(f"[4] cache hit {hit:.3f} s vs build {t1:.2f} s: {t1 / hit:.0f}x faster")


if __name__ == "__main__":
    tmp = Path(tempfile.mkdtemp(prefix="fluxmap-bench-"))
    try:
        estimators()
        paper3d_pose(tmp)
        jobs_and_cache(tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
