"""Print the reconstructed total next to the simulated truth (make demo-rig); exit 1 beyond 5 %.

$ python pipelines/rig_totals.py runs/demo-rig/reconstruction.h5
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


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "runs/demo-rig/reconstruction.h5"))
