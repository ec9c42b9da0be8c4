"""The T kernel's benchmark (issue 14, items 1-3): every figure measured in this one run,
repeated (min and median), ratios against references timed in the same run.

Run: ``python benchmarks/bench_transfer.py [--repeats N]`` (prints a table), or import and
call :func:`run` (the ``make bench`` driver does).

1. paper-3d, one pose (256 x 256 pixels, three views, 1600 elements): the lens T at its
   default sampling, its L1 error against a converged reference (a much finer lens T), wall
   time, rays/s, and rays/s as a fraction of raw embreex occlusion throughput on the same
   merged mesh and the very same rays (recorded by the kernel, cast once through embreex's
   own ``run(query="OCCLUDED")``, timed in this run).
2. The same T by ``pairwise`` at the paper's discretization (6 x 6 sub-triangles per face,
   3 x 3 sub-pixels): time and error against the same reference; the speed-up of ``lens``
   at equal or better accuracy (the cheapest lens sampling of a ladder whose error is at
   most pairwise's).
3. 1024 x 1024 pixels of 13 um, three views, a 20 000-element cylinder: time, peak memory
   (the resident peak of a child process that does only this build) and T's size.

Fewer rays for the same accuracy (issue 14), on both: "before" is the transfer-2 estimator
(every segment cast through Embree, the same lens points for every surface sample:
``skip_clear=False, turn_patterns=False``), "after" this one (faces whose whole lens cone is
provably clear are not cast, each sample's lens pattern turned); rays evaluated, segments
cast, wall time and L1 error against the converged reference, each pair in the same run.
On paper-3d "before" is the sampling item 1 needed before (>= 128 lens samples) and "after"
the cheapest sampling of the ladder at equal or better error; at 1024 x 1024 the default
sampling both times, the error measured on 600 random elements (columns are independent:
the others still occlude) against the reference sampling on the same elements.

Times on a shared machine are contended: the ratios within one run are the honest figures;
CPU seconds are given next to wall seconds.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fluxcli.config import load_config  # noqa: E402
from fluxcli.optics import transfer as TR  # noqa: E402
from fluxcli.optics.transfer import LensSampling, PairwiseSampling, build_transfer  # noqa: E402
from fluxcli.stages.plans import plan  # noqa: E402

# the converged reference: 3x the surface samples per pixel length (9x per area), 8x the
# lens samples per blur pixel and at least 256 lens samples per surface point (one round)
REFERENCE = LensSampling(surface_samples_per_pixel=6, lens_samples_min=256, lens_samples_max=16384,
                         lens_samples_per_blur_pixel=32, max_surface_subdivisions=96)
# lens samplings from cheap to fine: item 1 times the first whose error is <= 1 %, item 2 the
# first whose error is at most pairwise's (on paper-3d the error falls about as 1/lens samples:
# 2.1 %, 1.5 %, 0.8 % at 32, 64, 128 lens samples per surface point, 2 surface samples per pixel)
LADDER = [LensSampling(), LensSampling(lens_samples_min=64),
          LensSampling(surface_samples_per_pixel=1.5, lens_samples_min=128, lens_samples_per_blur_pixel=8),
          LensSampling(lens_samples_min=96), LensSampling(lens_samples_min=112), LensSampling(lens_samples_min=128),
          LensSampling(surface_samples_per_pixel=3, lens_samples_min=256)]
# what item 1 needed before (transfer-2: 0.79 % L1), the "before" of the rays-saved figure
BEFORE = LensSampling(lens_samples_min=128)
TRANSFER_2 = dict(skip_clear=False, turn_patterns=False)  # build_transfer as transfer-2 did
# cheaper than the default, for item 2: pairwise at the paper's discretization is far less
# accurate than the default lens T, so the fair comparison is the cheapest lens T at least as
# accurate as pairwise
CHEAP = [LensSampling(surface_samples_per_pixel=0.5, lens_samples_min=4, lens_samples_per_blur_pixel=0.5),
         LensSampling(surface_samples_per_pixel=0.5, lens_samples_min=8, lens_samples_per_blur_pixel=1),
         LensSampling(surface_samples_per_pixel=1, lens_samples_min=16, lens_samples_per_blur_pixel=2)]
PAPER_PAIRWISE = PairwiseSampling(surface_subdivisions=6, pixel_subdivisions=3)
TARGET_SECONDS, TARGET_FRACTION, TARGET_SPEEDUP = 2.0, 0.5, 20.0
BIG_SECONDS, BIG_GB = 60.0, 4.0


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _timed(fn, *a, **kw):
    t, c = time.perf_counter(), _cpu()
    out = fn(*a, **kw)
    return time.perf_counter() - t, _cpu() - c, out


def _desc(s: LensSampling) -> str:
    return (f"{s.surface_samples_per_pixel:g} surface samples/px, >= {s.lens_samples_min} lens samples "
            f"({s.lens_samples_per_blur_pixel:g}/blur px)")


def _l1(T, ref) -> float:
    return float(abs(T - ref).sum() / ref.sum())


def paper3d_scene():
    tmp = tempfile.mkdtemp(prefix="fluxmap-bench-")
    cfg = load_config(ROOT / "configs" / "paper-3d.yaml",
                      ["subject.poses.rotations_deg=[0]", f"transfer.cache_dir={tmp}", f"workdir={tmp}"])
    views, _, todo = plan(cfg)
    return views, todo[0][0]


def record_rays(scene, views, sampling: LensSampling = LensSampling()) -> np.ndarray:
    """The segments the lens kernel resolves for this pose (origin, unit direction, length),
    float32 (n, 7), recorded by the kernel itself, all of them cast (no visibility skipping)."""
    from fluxcli.optics import transfer_kernel
    from fluxcli.optics.raycast import OcclusionScene
    from fluxcli.surface.mesh import merge

    occ = OcclusionScene(*merge(scene.surface, *scene.occluders))
    nat = occ.native
    out = []
    for view in views:
        p = TR._lens_plan(scene.surface, view, sampling, 10**12)
        cam, m = view.camera, view.mirror
        n_pix = cam.nx * cam.ny
        rec = np.zeros((2 * p.rays, 7), np.float32)
        res = transfer_kernel.lens_columns(
            nat.occluded16, nat.scene, transfer_kernel.camera_record(cam), transfer_kernel.mirror_record(m),
            np.array([a.distance_mm for a in cam.apertures], float), np.array([a.radius_mm**2 for a in cam.apertures]),
            1e-3, p.points_mm, p.normals, p.edges_mm, p.ray_area_mm2, p.element, p.box_lo_mm, p.box_hi_mm,
            p.disk_center_mm, p.disk_radius_mm, p.use_box, p.n_lens, p.pat_off,
            p.disk_unit, p.square_unit, p.jitter, 0, len(p.points_mm), n_pix, cam.nx, cam.ny, np.zeros(n_pix),
            np.zeros(n_pix), np.zeros(n_pix, np.bool_), np.zeros(n_pix, np.int32), rec, p.clear,
            p.margin_mm, p.target, p.n_cap, p.spin, p.emis, p.tang, np.zeros((0, 2)), p.tframe)
        out.append(rec[:res[7]])
    return np.concatenate(out), occ


def _row(item, name, unit, values, target=None, met=None, note="", profile=None) -> dict:
    values = [float(v) for v in values]
    d = {"item": item, "name": name, "unit": unit, "min": min(values), "median": statistics.median(values),
         "target": target, "met": met, "note": note}
    if profile:
        d["profile"] = profile
    return d


def item1_and_2(repeats: int) -> list[dict]:
    views, scene = paper3d_scene()
    build_transfer(scene.surface, views, scene.occluders, lens_sampling=LensSampling(lens_samples_min=1))  # compile
    t_ref, c_ref, ref = _timed(build_transfer, scene.surface, views, scene.occluders, lens_sampling=REFERENCE)
    R = ref.T
    errors = {}

    def error_of(s: LensSampling) -> float:
        if s not in errors:
            errors[s] = _l1(build_transfer(scene.surface, views, scene.occluders, lens_sampling=s).T, R)
        return errors[s]

    # the cheapest sampling of the ladder at <= 1 % (else the finest)
    sampling = next((s for s in LADDER if error_of(s) <= 0.01), LADDER[-1])
    walls, cpus, rates, fracs, fracs_cpu, raw_rates = [], [], [], [], [], []
    res = None
    # every segment the estimator resolves (cast, or proven clear and not cast), as it would
    # cast them all: embreex casts all of them
    segs, occ = record_rays(scene, views, sampling)
    for _ in range(repeats):
        w, c, res = _timed(build_transfer, scene.surface, views, scene.occluders, lens_sampling=sampling)
        # raw embreex on the same merged mesh and the same rays, timed in this run
        rw, rc, _ = _timed(occ.blocked_embreex, segs[:, :3], segs[:, 3:6], segs[:, 6])
        walls.append(w)
        cpus.append(c)
        rates.append(len(segs) / w)
        raw_rates.append(len(segs) / rw)
        fracs.append(rw / w)
        fracs_cpu.append(rc / c)
    err_lens = _l1(res.T, R)
    est = float(np.nansum(res.column_error) / R.sum())
    rays = sum(s["rays"] for s in res.stats.values())
    profile = _profile(scene, views, sampling)
    from fluxcli.optics import embree_native

    nat, hit = occ.native, np.zeros(len(segs), bool)
    pw_, pc_, _ = _timed(embree_native.blocked_packets, nat.occluded16, nat.scene, segs[:, :3], segs[:, 3:6],
                         segs[:, 6], hit)
    raw_s = statistics.median([len(segs) / r for r in raw_rates])
    profile += (f"\n  Embree alone on the same {len(segs) / 1e6:.1f} M segments in 16-ray packets, one thread: "
                f"{pc_:.2f} s CPU ({pw_:.2f} s wall); embreex run() on them: {raw_s:.2f} s wall")
    ladder = ", ".join(f"{s.lens_samples_min} lens x {s.surface_samples_per_pixel:g} surface/px: {e:.4f}"
                       for s, e in errors.items())
    rows = [
        _row("1", "paper-3d lens T: L1 error vs converged reference", "fraction", [err_lens], "<= 0.01",
             err_lens <= 0.01, f"sampling {_desc(sampling)}; ladder errors: {ladder}; the stored per-column estimate "
             f"sums to {est:.4f}; reference {_desc(REFERENCE)} ({t_ref:.0f} s wall, {c_ref:.0f} s CPU)"),
        _row("1", "paper-3d lens T at <= 1 %: wall time", "s", walls, f"<= {TARGET_SECONDS}",
             min(walls) <= TARGET_SECONDS,
             f"{len(segs) / 1e6:.2f} M segments resolved, {rays / 1e6:.2f} M of them cast (the rest proven clear), "
             f"{TR.default_threads()} threads; CPU s min {min(cpus):.2f} median "
             f"{statistics.median(cpus):.2f}; contended machine", profile),
        _row("1", "paper-3d lens T: segments resolved/s", "rays/s", rates, None, None,
             f"raw embreex casting all of them: min {min(raw_rates):.3g} median {statistics.median(raw_rates):.3g} "
             f"rays/s"),
        _row("1", "rays/s as a fraction of raw embreex (wall)", "ratio", fracs, f">= {TARGET_FRACTION}",
             statistics.median(fracs) >= TARGET_FRACTION,
             f"same {len(segs) / 1e6:.2f} M segments through embreex run(query='OCCLUDED'), one thread (it holds "
             f"the GIL); per CPU second: min {min(fracs_cpu):.2f} median {statistics.median(fracs_cpu):.2f}"),
    ]
    rows += _rays_saved_paper3d(scene, views, R, error_of, repeats)
    # 2. pairwise at the paper's discretization, and lens at equal or better accuracy
    pw_walls, pw = [], None
    for _ in range(max(1, min(repeats, 2))):
        w, _, pw = _timed(build_transfer, scene.surface, views, scene.occluders, estimator="pairwise",
                          pairwise_sampling=PAPER_PAIRWISE)
        pw_walls.append(w)
    err_pw = _l1(pw.T, R)
    chosen, lens_walls, err_l = None, [], None
    for s in CHEAP + LADDER:
        err_l = error_of(s)
        if err_l <= err_pw:
            chosen = s
            # a build of a few tens of ms: time it often enough (>= 10 times) that one scheduler hiccup
            # is not the figure
            lens_walls = [_timed(build_transfer, scene.surface, views, scene.occluders, lens_sampling=s)[0]
                          for _ in range(max(repeats, 10))]
            break
    rows.append(_row("2", "paper-3d pairwise (6x6 sub-triangles, 3x3 sub-pixels): wall time", "s", pw_walls, None,
                     None, f"L1 error vs the same reference {err_pw:.4f}; "
                           f"{sum(s['rays'] for s in pw.stats.values()) / 1e6:.1f} M rays cast"))
    if chosen is not None:
        speed = [statistics.median(pw_walls) / x for x in lens_walls]
        rows.append(_row("2", "lens speed-up over pairwise at equal or better accuracy", "x", speed,
                         f">= {TARGET_SPEEDUP}", statistics.median(speed) >= TARGET_SPEEDUP,
                         f"lens {_desc(chosen)}: error {err_l:.4f} <= pairwise {err_pw:.4f}; pairwise median "
                         f"{statistics.median(pw_walls):.2f} s over each lens time; met on the median, as item 1's "
                               f"fraction (a lens build of tens of ms: one scheduler hiccup sets the min)"))
    else:
        rows.append(_row("2", "lens speed-up over pairwise at equal or better accuracy", "x", [float("nan")],
                         f">= {TARGET_SPEEDUP}", False, f"no lens sampling of the ladder reached pairwise's "
                                                         f"{err_pw:.4f} (finest: {err_l:.4f})"))
    return rows


def _counts(res) -> tuple[float, float]:
    """(rays evaluated, segments cast) of a build."""
    return (sum(s["rays_evaluated"] for s in res.stats.values()), sum(s["rays"] for s in res.stats.values()))


def _rays_saved_paper3d(scene, views, R, error_of, repeats) -> list[dict]:
    """Item 1's "before" (transfer-2 at the sampling it needed for <= 1 %) against the
    cheapest sampling of the ladder at equal or better error, timed alternately."""
    build = lambda s, **kw: build_transfer(scene.surface, views, scene.occluders, lens_sampling=s, **kw)  # noqa: E731
    before = build(BEFORE, **TRANSFER_2)
    err_b = _l1(before.T, R)
    after_s = next((s for s in LADDER if error_of(s) <= err_b), BEFORE)
    after = build(after_s)
    err_a = _l1(after.T, R)
    wb, wa = [], []
    for _ in range(repeats):
        wb.append(_timed(build, BEFORE, **TRANSFER_2)[0])
        wa.append(_timed(build, after_s)[0])
    (eb, cb), (ea, ca) = _counts(before), _counts(after)
    note = (f"before (transfer-2, {_desc(BEFORE)}): {eb / 1e6:.1f} M rays, {cb / 1e6:.1f} M segments cast, "
            f"L1 {err_b:.4f}, {statistics.median(wb):.2f} s; after ({_desc(after_s)}): {ea / 1e6:.1f} M rays, "
            f"{ca / 1e6:.1f} M segments cast, L1 {err_a:.4f}, {statistics.median(wa):.2f} s (median wall)")
    return [
        _row("1", "paper-3d rays saved at equal or better error: rays after/before", "ratio", [ea / eb], None, None,
             note),
        _row("1", "paper-3d segments cast after/before (visibility + sampling)", "ratio", [ca / cb], None, None,
             "before casts every segment; after casts none for faces whose whole lens cone is provably clear"),
        _row("1", "paper-3d wall time after/before at equal or better error", "ratio",
             [a / b for a, b in zip(wa, wb)], None, None, f"L1 error before {err_b:.4f}, after {err_a:.4f}"),
    ]


def _profile(scene, views, sampling) -> str:
    """Where one paper-3d build spends its time (cProfile, top functions by own time)."""
    import cProfile
    import io
    import pstats

    pr = cProfile.Profile()
    pr.enable()
    build_transfer(scene.surface, views, scene.occluders, threads=1, lens_sampling=sampling)
    pr.disable()
    buf = io.StringIO()
    st = pstats.Stats(pr, stream=buf)
    total = st.total_tt
    lines = [f"one thread, {total:.2f} s under cProfile:"]
    for (file, _, fn), (_, _, tt, _, _) in sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:6]:
        lines.append(f"  {tt / total:5.1%} {tt:6.2f} s  {Path(file).name}:{fn}")
    return "\n".join(lines)


BIG = ["system.camera.pixels=[1024,1024]", "system.camera.pixel_pitch_mm=0.013",
       "subject.surface.n_angular=200", "subject.surface.n_axial=100", "subject.poses.rotations_deg=[0]"]


def big_scene():
    tmp = tempfile.mkdtemp(prefix="fluxmap-bench-big-")
    cfg = load_config(ROOT / "configs" / "paper-3d.yaml", BIG + [f"transfer.cache_dir={tmp}", f"workdir={tmp}"])
    views, _, todo = plan(cfg)
    return views, todo[0][0]


def _big_child(before: bool = False) -> None:
    """Item 3 in a process of its own (so that its peak memory is its own): prints JSON."""
    views, scene = big_scene()
    kw = TRANSFER_2 if before else {}
    w, c, res = _timed(build_transfer, scene.surface, views, scene.occluders, **kw)
    T = res.T
    print(json.dumps({"seconds": w, "cpu_seconds": c, "elements": scene.surface.n_elements, "nnz": int(T.nnz),
                      "bytes": int(T.data.nbytes + T.indices.nbytes + T.indptr.nbytes),
                      "rays": sum(s["rays"] for s in res.stats.values()),
                      "rays_evaluated": sum(s["rays_evaluated"] for s in res.stats.values()),
                      "peak_bytes": _peak_rss_bytes()}))


def _peak_rss_bytes() -> int:
    """This process's resident peak.  VmHWM (Linux) starts afresh at exec; ru_maxrss does not
    (a child forked from a big parent would report the parent's size)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _big_errors(n_elements: int = 600) -> tuple[float, float, str]:
    """L1 error of the default 1024 x 1024 T before (transfer-2) and after, on ``n_elements``
    random elements (the others still occlude) against the reference sampling on them."""
    from fluxcli.surface.mesh import Surface

    views, scene = big_scene()
    S = scene.surface
    pick = np.random.default_rng(0).choice(S.n_elements, n_elements, replace=False)
    sub = Surface(S.vertices_mm, S.faces, np.where(np.isin(S.element_of_face, pick), S.element_of_face, -1),
                  S.n_elements)
    occ = [S, *scene.occluders]  # the whole subject occludes (its emitting faces twice: coplanar, harmless)
    t, _, ref = _timed(build_transfer, sub, views, occ, lens_sampling=REFERENCE)
    R = ref.T
    before = _l1(build_transfer(sub, views, occ, **TRANSFER_2).T, R)
    after = _l1(build_transfer(sub, views, occ).T, R)
    return before, after, (f"{n_elements} random elements, reference {_desc(REFERENCE)} on them ({t:.0f} s wall, "
                           f"its own estimate {np.nansum(ref.column_error) / R.sum():.4f})")


def item3(repeats: int) -> list[dict]:
    walls, peaks, out = [], [], None
    walls_before, out_before, cpus, cpus_before = [], None, [], []
    for _ in range(repeats):
        p = subprocess.run([sys.executable, __file__, "--big-child"], capture_output=True, text=True, check=True)
        out = json.loads(p.stdout.strip().splitlines()[-1])
        walls.append(out["seconds"])
        cpus.append(out["cpu_seconds"])
        peaks.append(out["peak_bytes"] / 1e9)
        p = subprocess.run([sys.executable, __file__, "--big-child", "--before"], capture_output=True, text=True,
                           check=True)
        out_before = json.loads(p.stdout.strip().splitlines()[-1])
        walls_before.append(out_before["seconds"])
        cpus_before.append(out_before["cpu_seconds"])
    err_b, err_a, how = _big_errors()
    saved = [
        _row("3", "1024x1024: segments cast after/before (visibility)", "ratio",
             [out["rays"] / out_before["rays"]], None, None,
             f"before (transfer-2): {out_before['rays_evaluated'] / 1e6:.0f} M rays, {out_before['rays'] / 1e6:.0f} M "
             f"segments cast, L1 {err_b:.4f}; after: {out['rays_evaluated'] / 1e6:.0f} M rays, "
             f"{out['rays'] / 1e6:.0f} M segments cast, L1 {err_a:.4f} (errors on {how})"),
        _row("3", "1024x1024: wall time after/before, same sampling", "ratio",
             [a / b for a, b in zip(walls, walls_before)], None, None,
             f"before median {statistics.median(walls_before):.1f} s, after {statistics.median(walls):.1f} s "
             f"(alternating child processes); L1 error before {err_b:.4f}, after {err_a:.4f}"),
        _row("3", "1024x1024: CPU time after/before, same sampling", "ratio",
             [a / b for a, b in zip(cpus, cpus_before)], None, None,
             f"before median {statistics.median(cpus_before):.1f} s CPU, after {statistics.median(cpus):.1f} s CPU"),
    ]
    return saved + [
        _row("3", "1024x1024 px (13 um), 3 views, 20 000 elements: wall time", "s", walls, f"<= {BIG_SECONDS}",
             min(walls) <= BIG_SECONDS, f"{out['rays_evaluated'] / 1e6:.0f} M rays ({out['rays'] / 1e6:.0f} M "
                                        f"segments cast), {out['elements']} elements, CPU "
                                        f"{out['cpu_seconds']:.1f} s (last run); contended machine"),
        _row("3", "1024x1024 px, 20 000 elements: peak memory", "GB", peaks, f"<= {BIG_GB}", max(peaks) <= BIG_GB,
             "resident peak (VmHWM) of a child process doing only this build"),
        _row("3", "1024x1024 px, 20 000 elements: T size", "MB", [out["bytes"] / 1e6], None, None,
             f"nnz {out['nnz']:,} (CSR data + indices + indptr in memory)"),
    ]


def run(repeats: int = 3) -> list[dict]:
    """Items 1-3 of issue 14's benchmark; rows as the ``make bench`` driver expects."""
    return item1_and_2(repeats) + item3(repeats)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--big-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--before", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--items", default="1,2,3", help="which items: 1,2 (one run, they share the reference) and/or 3")
    a = ap.parse_args()
    if a.big_child:
        _big_child(a.before)
        return
    print(f"{'item':4} {'name':64} {'min':>11} {'median':>11} {'unit':7} {'target':9} met", flush=True)
    rows = []
    wanted = set(a.items.split(","))
    for item in [f for f, keys in ((item1_and_2, {"1", "2"}), (item3, {"3"})) if keys & wanted]:
        got = item(a.repeats)
        rows += got
        for r in got:
            print(f"{r['item']:4} {r['name'][:64]:64} {r['min']:11.4g} {r['median']:11.4g} {r['unit']:7} "
                  f"{r['target'] or '':9} {'' if r['met'] is None else ('yes' if r['met'] else 'NO')}")
            print(f"     {r['note']}", flush=True)
    for r in rows:
        if r.get("profile"):
            print(r["profile"])
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
