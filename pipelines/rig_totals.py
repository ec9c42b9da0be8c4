"""Print the reconstructed total next to the simulated truth (make demo-rig); exit 1 beyond 5 %.

$ python pipelines/rig_totals.py runs/demo-rig/reconstruction.h5
$ python pipelines/rig_totals.py runs/demo-rig-captured/reconstruction.h5 runs/demo-rig/reconstruction.h5
  (also: the total within 2 % of the same frames reconstructed on the reference's surface)
"""

import sys

import h5py
import numpy as np

TOLERANCE = 0.05


def main(path: str) -> int:
    with h5py.File(path, "r") as f:
        total = float(f["flux/total"][()])
        observed = f["flux/observed"][()].astype(bool)
        if "truth" not in f:
            print(f"{path}: reconstructed total {total:.4g} photons (no truth recorded: not a simulated camera)")
            return 0
        truth = f["truth/power"][()]
    whole, seen = float(truth.sum()), float(truth[observed].sum())
    ratio = total / whole
    print(f"reconstructed total   {total:.4g} photons per exposure ({observed.mean():.0%} of the elements observed)")
    print(f"simulated truth       {whole:.4g} photons per exposure (on the observed elements: {seen:.4g})")
    print(f"ratio                 {ratio:.4f}  ({'within' if abs(ratio - 1) <= TOLERANCE else 'NOT within'} "
          f"{TOLERANCE:.0%})")
    return 0 if abs(ratio - 1) <= TOLERANCE else 1


def against(path: str, reference: str, tolerance: float = 0.02) -> int:
    """The same frames reconstructed on another surface (e.g. the captured mesh): totals within 2 %."""
    with h5py.File(path, "r") as f, h5py.File(reference, "r") as g:
        a, b = float(f["flux/total"][()]), float(g["flux/total"][()])
        truth = float(g["truth/power"][()].sum()) if "truth" in g else None
    ok = abs(a / b - 1) <= tolerance
    print(f"against {reference}: total {b:.4g}, ratio {a / b:.4f}  ({'within' if ok else 'NOT within'} {tolerance:.0%})")
    if truth is not None:  # the same frames: the reference's truth is this run's truth
        ok_t = abs(a / truth - 1) <= TOLERANCE
        print(f"against the simulated truth {truth:.4g} recorded there: ratio {a / truth:.4f}  "
              f"({'within' if ok_t else 'NOT within'} {TOLERANCE:.0%})")
        ok &= ok_t
    return 0 if ok else 1


if __name__ == "__main__":
    rc = main(sys.argv[1] if len(sys.argv) > 1 else "runs/demo-rig/reconstruction.h5")
    if len(sys.argv) > 2:
        rc = max(rc, against(sys.argv[1], sys.argv[2]))
    sys.exit(rc)
