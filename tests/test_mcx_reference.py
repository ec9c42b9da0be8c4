"""The ``diffuse`` emission profile against photons that MCX let out of a turbid box.

The table ``data-samples/reference/mcx_box_n140.csv`` was made by
``benchmarks/mcx_reference.py``: MCX-CL (pmcxcl, run on CPU through pocl) transported photons
through issue 21's box (30 x 40 x 20 mm, mu_a 0.01 /mm, mu_s 1 /mm, g 0, n 1.40 in air, an
isotropic source 6 mm under the top face) and recorded every photon that left it.  Its rows are
the radiance leaving the top face, away from the edges, in 5-degree bands of the exit angle,
relative to the radiance along the normal, with Monte Carlo standard errors.  fluxmap's profile
did not make any of these numbers.  ``mcx_box_n133.csv`` and ``mcx_box_n156.csv`` are the same box
at n 1.33 and 1.56 (``--refractive-index``), 1.2e7 photons each.

Measured (diffuse at the table's own n, worst band from 5 to 75 degrees, in units of L(0)):
n 1.33 +0.019 at 65 deg (SE 0.003), n 1.40 +0.015 at 70 deg, n 1.56 +0.014 at 65 deg.
Diffusion theory puts slightly too much light at grazing angles, most at the lowest n.

Each band of the table is a cos(theta) sin(theta)-weighted mean of L over the band, so the
profile is averaged over the same band with the same weight before the two are compared (no
bias from the bands' width, which for the diffuse curve is 0.3 % of L(0) at 80 degrees).
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "data-samples" / "reference"
TABLE = REFERENCE / "mcx_box_n140.csv"  # the issue's box
INDICES = (1.33, 1.40, 1.56)  # the same box at the ends of the issue's range of n, too


def table_path(n: float) -> Path:
    return REFERENCE / f"mcx_box_n{round(100 * n):d}.csv"

TOL_OF_L0 = 0.02  # issue 21: within 2 % of L(0) up to 75 degrees
Z = 2.5  # a difference is charged to the model only beyond Z standard errors of the table
MAX_SE = 0.006  # the table must be able to tell a 2 % miss from its noise where it is used
UP_TO_DEG = 75.0

# Issue 21: L(theta)/L(0) from 2e9 MCX photons in the same box.
ISSUE_MCX = {30.0: 0.972, 45.0: 0.936, 60.0: 0.873, 70.0: 0.781, 80.0: 0.563}


def read_table(path: Path = TABLE) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    head, body = rows[0], np.array(rows[1:], dtype=float)
    return {name: body[:, i] for i, name in enumerate(head)}


def header(path: Path = TABLE) -> str:
    return "".join(line for line in open(path) if line.startswith("#"))


def band_mean(radiance, lo_deg: float, hi_deg: float, m: int = 64) -> float:
    """The cos-sin-weighted mean over [lo, hi] of ``radiance(theta_rad)``, as the table's bands."""
    x, w = np.polynomial.legendre.leggauss(m)
    lo, hi = np.radians(lo_deg), np.radians(hi_deg)
    th = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
    wt = w * np.cos(th) * np.sin(th)
    return float(np.sum(wt * radiance(th)) / np.sum(wt))


def _absent(path: Path) -> str:
    return (f"{path.relative_to(ROOT)} is absent: make it with benchmarks/mcx_reference.py "
            "(needs pmcxcl + OpenCL)")


needs_table = pytest.mark.skipif(not TABLE.exists(), reason=_absent(TABLE))
each_index = pytest.mark.parametrize("n", [
    pytest.param(n, marks=pytest.mark.skipif(not table_path(n).exists(), reason=_absent(table_path(n))))
    for n in INDICES
])


def compared_bands(t: dict[str, np.ndarray]) -> np.ndarray:
    # From the 5-degree band on: the half band at 0 has 0.2 % of the photons and went into L(0).
    return (t["theta_centre_deg"] >= 5.0) & (t["theta_centre_deg"] <= UP_TO_DEG)


@each_index
def test_table_is_what_its_script_says(n):
    """The table records how it was made, and its photons left the box where they should."""
    h = header(table_path(n))
    assert f"n {n} in air" in h
    assert "made by benchmarks/mcx_reference.py" in h
    assert re.search(r"pmcxcl \d+\.\d+\.\d+ \(MCX-CL", h)
    assert "issrcfrom0=1" in h  # the source where the issue puts it, not one voxel off
    y, y_se = map(float, re.search(r"mean y of top-face exits ([\d.]+) \+- ([\d.]+)", h).groups())
    assert abs(y - 20.0) < 4 * y_se + 1e-9
    t = read_table(table_path(n))
    assert np.all(np.diff(t["theta_lo_deg"]) > 0) and t["theta_hi_deg"][-1] == 90.0
    # The fit's L(0) and the first bands agree (the fit is not an extrapolation artefact).
    near = t["theta_centre_deg"] <= 15
    assert np.all(np.abs(t["L_rel"][near] - 1) < 0.01 + 3 * t["L_rel_se"][near])
    # Radiance falls towards grazing angles, as it must behind a Fresnel boundary.
    assert t["L_rel"][t["theta_centre_deg"] == 85.0][0] < 0.5


@each_index
def test_diffuse_profile_within_2_percent_of_mcx_up_to_75_degrees(n):
    from fluxcli.optics.emission import profile

    t = read_table(table_path(n))
    use = compared_bands(t)
    assert use.sum() == 15
    se = t["L_rel_se"][use]
    assert np.all(se <= MAX_SE), f"the table is too noisy to judge 2 %: SE up to {se.max():.4f}"
    diffuse = profile({"model": "diffuse", "refractive_index": n})
    model = np.array([band_mean(diffuse.radiance, lo, hi)
                      for lo, hi in zip(t["theta_lo_deg"][use], t["theta_hi_deg"][use])])
    diff = model - t["L_rel"][use]
    excess = np.abs(diff) - Z * se
    worst = int(np.argmax(excess))
    assert np.all(excess <= TOL_OF_L0), (
        f"diffuse misses MCX by {diff[worst]:+.4f} of L(0) at {t['theta_centre_deg'][use][worst]:g} deg "
        f"(table SE {se[worst]:.4f})"
    )


@needs_table
def test_lambertian_fails_the_same_check():
    """The check can fail: the Lambertian profile (L/L0 = 1) misses the photons beyond 60 degrees."""
    from fluxcli.optics.emission import profile

    t = read_table()
    lam = profile({"model": "lambertian"})
    use = compared_bands(t)
    model = np.array([band_mean(lam.radiance, lo, hi)
                      for lo, hi in zip(t["theta_lo_deg"][use], t["theta_hi_deg"][use])])
    excess = np.abs(model - t["L_rel"][use]) - Z * t["L_rel_se"][use]
    assert np.max(excess) > TOL_OF_L0
    assert np.sum(excess > TOL_OF_L0) >= 3  # 60-75 degrees at least


@needs_table
def test_table_agrees_with_the_issues_mcx_run():
    """Two MCX runs (the issue's 2e9 photons on a GPU, this table on a CPU) give the same curve.

    The issue's values are L at the angle (how it binned is not stated); the table's are band
    means, which near 80 degrees sit above L at the centre by ~0.3 % of L(0) (the weight
    cos sin falls across the band): 0.01 of L(0) covers that and the issue's rounding.  The
    largest gap is at 80 degrees: the table's band is 0.014 above the issue's 0.563 (0.011 after
    the band bias), inside 0.01 + 2.5 SE; how the issue binned and where its source sat (MCX's
    default 1-based srcpos puts it 1 mm deeper) are not known."""
    t = read_table()
    for deg, ref in ISSUE_MCX.items():
        i = int(np.flatnonzero(t["theta_centre_deg"] == deg)[0])
        assert abs(t["L_rel"][i] - ref) <= 0.01 + Z * t["L_rel_se"][i], (deg, t["L_rel"][i], ref)


GPU_TABLE = REFERENCE / "mcx_box_n140_gpu.csv"  # 5e8 photons, pmcx (CUDA) on an H200


@pytest.mark.skipif(not GPU_TABLE.exists(), reason=_absent(GPU_TABLE))
def test_diffuse_profile_within_2_percent_of_5e8_gpu_mcx_photons_up_to_75_degrees():
    """The same box by MCX on a GPU (benchmarks/issue21_mcx.py, 5e8 photons): its standard
    errors are 5e-4 of L(0), so the 2 % bar is tested on the model's own miss, not on noise.
    Measured: diffuse lies above the photons by 0.006 at 30, 0.011 at 45, 0.015 at 60, 0.016
    at 65 (the worst) and 0.015 at 75 degrees.  The CPU table (MCX-CL) agrees with it within
    1.8 of their combined standard errors in every band: two devices, one curve."""
    from fluxcli.optics.emission import profile

    h = header(GPU_TABLE)
    assert "made by benchmarks/issue21_mcx.py" in h and "photons launched 500000000" in h
    gpu, cpu = read_table(GPU_TABLE), read_table()
    use = compared_bands(gpu)
    assert np.all(gpu["L_rel_se"][use] < 0.001)
    diffuse = profile({"model": "diffuse", "refractive_index": 1.40})
    model = np.array([band_mean(diffuse.radiance, lo, hi)
                      for lo, hi in zip(gpu["theta_lo_deg"][use], gpu["theta_hi_deg"][use])])
    assert np.all(np.abs(model - gpu["L_rel"][use]) <= TOL_OF_L0)
    z = (cpu["L_rel"][use] - gpu["L_rel"][use]) / np.hypot(cpu["L_rel_se"][use], gpu["L_rel_se"][use])
    assert np.all(np.abs(z) < 3.5)
    lam = np.ones(use.sum())  # and the check can fail: Lambertian misses beyond ~50 degrees
    assert np.sum(np.abs(lam - gpu["L_rel"][use]) > TOL_OF_L0) >= 6


# ---------------------------------------------------------------- live MCX (optional)
def _live_mcx_or_skip():
    from repo_scripts import load_script

    ref = load_script("benchmarks/mcx_reference.py")
    try:
        pmcxcl = ref.load_pmcxcl()
    except ImportError as exc:
        pytest.skip(f"pmcxcl is not installed ({exc}); pip install -e .[mcx] to run MCX live")
    if not ref.opencl_devices(pmcxcl):
        pytest.skip("pmcxcl found no OpenCL device (Debian: apt-get install pocl-opencl-icd)")
    return ref, pmcxcl


@needs_table
def test_live_mcx_run_reproduces_the_table(tmp_path):
    """Where pmcxcl and an OpenCL device exist: a fresh, small MCX run (other seeds) agrees with
    the committed table within its own noise (escaped fraction, its share through the top face,
    and the curve)."""
    ref, pmcxcl = _live_mcx_or_skip()
    out = tmp_path / "live.csv"
    assert ref.main(["--nphoton", "1.5e5", "--chunk", "1.5e5", "--seed", "7", "--out", str(out)]) == 0
    small, table = read_table(out), read_table()
    esc = [float(re.search(r"escaped fraction ([\d.]+) \+- ([\d.]+)", header(p)).group(g))
           for p in (out, TABLE) for g in (1, 2)]
    assert abs(esc[0] - esc[2]) < 4 * np.hypot(esc[1], esc[3])
    top = [float(re.search(r"z20_top ([\d.]+)\+-([\d.]+)", header(p)).group(g))
           for p in (out, TABLE) for g in (1, 2)]
    assert abs(top[0] - top[2]) < 4 * np.hypot(top[1], top[3])
    use = (small["theta_centre_deg"] >= 20) & (small["theta_centre_deg"] <= 80)
    se = np.hypot(small["L_rel_se"][use], table["L_rel_se"][use])
    assert np.all(np.abs(small["L_rel"][use] - table["L_rel"][use]) < 4 * se)


# ---------------------------------------------------------------- fluxmap's own Monte Carlo
@needs_table
@pytest.mark.slow
def test_fluxmap_montecarlo_agrees_with_mcx():
    """fluxmap's numba photon transport (fluxcli.montecarlo) in the same box gives MCX's escaped
    fraction, share through the top face and exit-angle curve, within the two codes' noise
    (4e6 photons, ~55 s).  Measured with 1e7 photons: escaped 0.39447 +- 0.00015 (MCX 0.39449
    +- 0.00013), top face 0.23938 (MCX 0.23941); the curve within 0.015 of L(0) (2.7 SE) from 5
    to 80 degrees.  MCX's box at n 1.33 escapes 0.406, 60 SE away: the check can tell."""
    from fluxcli.montecarlo.transport import Medium, Shape, Tally, transport

    n_photons, batch = 4_000_000, 500_000
    size = (30.0, 40.0, 20.0)
    source = np.array([5.0, 0.0, 4.0])  # MCX's (20, 20, 14) in a box centred on the origin
    tally, pos, dirs = Tally(), [], []
    for b in range(n_photons // batch):
        esc = transport(Medium(0.01, 1.0, 0.0, 1.40), Shape.box(size), source, batch,
                        seed=11, batch=b, tally=tally)
        pos.append(esc.position_mm)
        dirs.append(esc.direction)
    pos, dirs = np.concatenate(pos), np.concatenate(dirs)
    n = tally.launched
    h = header()

    def mcx(pattern):
        return [float(v) for v in re.search(pattern, h).groups()]

    esc_mcx, esc_mcx_se = mcx(r"escaped fraction ([\d.]+) \+- ([\d.]+)")
    top_mcx, top_mcx_se = mcx(r"z20_top ([\d.]+)\+-([\d.]+)")
    esc = tally.escaped / n
    assert abs(esc - esc_mcx) < 4 * np.hypot(np.sqrt(esc * (1 - esc) / n), esc_mcx_se)
    top = np.abs(pos[:, 2] - size[2] / 2) < 1e-6
    share = top.sum() / n
    assert abs(share - top_mcx) < 4 * np.hypot(np.sqrt(share * (1 - share) / n), top_mcx_se)

    # The curve, binned and normalised by benchmarks/mcx_reference.py's own tally: the photons
    # as MCX would record them (corner origin, path 0 and weight 1: analogue transport).
    from repo_scripts import load_script

    ref = load_script("benchmarks/mcx_reference.py")
    det = np.vstack([np.zeros(len(pos)), (pos + np.array(size) / 2).T, dirs.T, np.ones(len(pos))])
    mine = ref.Tally(edge_mm=5.0)
    mine.add(det, {"energytot": n, "energyabs": n - len(pos)}, n)
    rad, rad_se = mine.radiance()
    l0, l0_se, _ = mine.l0_fit()
    rel = rad / l0
    rel_se = rel * np.hypot(rad_se / rad, l0_se / l0)
    t = read_table()
    use = (t["theta_centre_deg"] >= 5) & (t["theta_centre_deg"] <= 85)
    z = np.abs(rel[use] - t["L_rel"][use]) / np.hypot(rel_se[use], t["L_rel_se"][use])
    assert np.all(z < 4), f"fluxmap MC and MCX differ by {z.max():.1f} SE at some band"


def test_a_batch_tallied_in_slices_and_merged_is_the_batch_tallied_whole():
    """The GPU run tallies each batch's packets in worker processes, slice by slice
    (benchmarks/issue21_mcx.py): the merged sums must be those of one tally of the whole batch,
    and a slice alone must not pass as a run (its launched photons are added once, by the run)."""
    from repo_scripts import load_script

    ref = load_script("benchmarks/mcx_reference.py")
    rng = np.random.default_rng(7)
    n = 50_000
    pos = rng.uniform(0, 1, (3, n)) * np.array(ref.SIZE_MM, float)[:, None]
    face = rng.integers(0, 3, n)  # put every packet on a face: x, y or z, low or high side
    side = rng.integers(0, 2, n)
    pos[face, np.arange(n)] = side * np.array(ref.SIZE_MM, float)[face]
    v = rng.normal(size=(3, n))
    v /= np.linalg.norm(v, axis=0)
    top = (face == 2) & (side == 1)
    v[2, top] = np.abs(v[2, top])
    det = np.vstack([rng.uniform(0, 60, n), pos, v, rng.uniform(0.2, 1, n)])
    stat = {"energytot": 2.0e5, "energyabs": 1.2e5}
    whole = ref.Tally(5.0)
    whole.add(det, stat, 200_000)
    merged = ref.Tally(5.0)
    for a, b in ((0, 1), (1, 17_000), (17_000, 31_000), (31_000, n)):
        part = ref.Tally(5.0)
        part.add(det[:, a:b], None, 0, check=False)
        assert part.n_launched == 0 and part.mcx_escaped == 0
        merged.merge(part)
    merged.add_run(stat, 200_000)
    merged.check()
    assert whole.band_n.sum() > 1000 and whole.n_unplaced == 0
    for k, val in vars(whole).items():
        np.testing.assert_allclose(getattr(merged, k), val, rtol=1e-12, err_msg=k)
