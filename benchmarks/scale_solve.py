"""One reconstruction of issue 22's scene, the way the reconstruct stage solves a pose, with a chosen
path; prints one JSON line (time, CPU, accuracy against the truth).  Run in a subprocess by
bench_scale.py, which measures its peak memory (os.wait4).

Run: .venv/bin/python benchmarks/scale_solve.py runs/scale-50000/scale.yaml matfree
     [--crime]  images from the reconstruction's own T (noiseless x Poisson): for timing a size
                whose honest simulation is too slow to make (200 000 elements); its accuracy means
                nothing and is not printed
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def main(argv=None) -> int:
    import h5py
    import numpy as np

    from fluxcli.artefacts.transfer import load_T
    from fluxcli.config import load_config
    from fluxcli.imaging import noise as N
    from fluxcli.inverse import error_l1, reconstruct, total_ratio
    from fluxcli.stages.plans import plan
    from fluxcli.workers import blas_threads

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("solver", choices=["dense", "matfree", "auto"])
    ap.add_argument("--crime", action="store_true")
    a = ap.parse_args(argv)
    cfg = load_config(a.config, [])
    _, placer, todo = plan(cfg)
    surf = placer.surface
    T = load_T(todo[0][1].path).tocsr()
    if a.crime:
        x = surf.element_centroids_mm
        c = x[np.argmax(x[:, 2])]
        truth = 0.05 + np.exp(-0.5 * np.sum((x - c) ** 2, axis=1) / 25.0)
        a0 = T @ truth
        img = np.random.default_rng(0).poisson(a0 * 900.0 / a0.max()).astype(float)
        truth = truth * 900.0 / a0.max()
    else:
        with h5py.File(cfg.workdir / "simulation.h5") as f:
            img = f["images/noisy"][0, 0, 0].astype(float).ravel()
            truth = f["truth/power"][()] * f["truth/level_scale"][0]
    noise = N.PhotonNoise("poisson")
    t, c0 = time.perf_counter(), time.process_time()
    with blas_threads(1):
        r = reconstruct(T, img, method="smooth", variance=noise.variance, adjacency=surf.element_adjacency(),
                        areas=surf.element_areas_mm2, solver=a.solver)
    out = {"n_elements": int(surf.n_elements), "n_unknowns": int(r.observed.sum()), "solver": a.solver,
           "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c0, "lam": r.lam,
           "total": float(np.nansum(r.power)), "chi2": r.chi2_per_pixel, "warnings": list(r.warnings),
           "nnz_T": int(T.nnz)}
    if not a.crime:
        out |= {"error": error_l1(r.power, truth), "total_ratio": total_ratio(r.power, truth),
                "error_observed": error_l1(np.where(r.observed, r.power, np.nan), truth, observed_only=True),
                "total_ratio_observed": total_ratio(np.where(r.observed, r.power, np.nan), truth, observed_only=True)}
    import resource

    # a dense solve runs in a child process (fluxcli.inverse._threads.in_child): its peak too
    out["peak_children_gb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
