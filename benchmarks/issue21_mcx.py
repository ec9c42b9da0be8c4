"""Issue 21's two box experiments at the issue's own photon count: photons transported by MCX
(pmcx, CUDA) on a GPU machine and imaged there on every CPU core; reconstructed here.

The box, source, camera, mirrors, poses and surfaces are those of ``issue21_box.py``
(``direct``: 9 poses; ``mirrors``: 6 rotations x 2 heights, two 45° mirrors). MCX runs the
phantom as ``mcx_reference.py`` does (1-mm voxels, Fresnel at every face, every face a detector,
``savedetflag='dpxvw'``: exit point, direction after refraction into air, initial weight, path
length). Each detected packet leaves with weight w0 exp(-μa L); it is kept as one whole photon
with that probability (Russian roulette), so the images are whole photons, as in the issue. The
truth per element is the photons that left through it; the images are the same photons traced
through the thin lens and the mirrors (``fluxcli.montecarlo.camera``). No emission model enters,
except in ``direct-control``, the issue's control: the same exit points with directions redrawn
from diffuse(1.40).

    # here: the geometry the GPU machine needs (views, poses, occluders, truth surface) + wheels
    $ .venv/bin/python benchmarks/issue21_mcx.py prepare
    # on the GPU machine, in the repository's root with .gpu21 carried (see prepare's output);
    # install the wheels with `python3 -m pip` (a bare `pip` there may serve another interpreter):
    $ python3 -m pip install --no-index --no-deps --break-system-packages .gpu21/whl/*.whl
    $ PYTHONPATH=. python3 benchmarks/issue21_mcx.py transport --photons 1.2e10 --split 2e9 --seconds 380 --seed 35000 --out $OUT/d.npz
    # (``--split 2e9``: a file per 2e9 photons, each an independent run of the issue's size; at most
    # 8 files come back from $OUT, so at most 6 parts beside the CSV and a log.  benchmarks/issue21_gpu.sh does all this)
    # here: the photons' images into simulation artefacts; diffuse and lambertian reconstructed
    $ .venv/bin/python benchmarks/issue21_mcx.py reconstruct runs/issue21/mcx/issue21_mcx.npz
    # here: every whole photon by face and exit angle against diffuse(1.40) (runs from 26 Nov 2026 on)
    $ .venv/bin/python benchmarks/issue21_mcx.py bands runs/issue21/mcx-cpu3/issue21_mcx_cl_s26000.npz

``transport --backend pmcxcl`` runs the same code here with MCX-CL on CPU (pocl) for a small check.
The exit-angle radiance of the top face (``mcx_reference.Tally``, the reference CSV's method) is
accumulated from every packet and written beside the images as ``mcx_box_n140_gpu.csv``.

The parent process runs MCX and nothing else: it writes each batch's detected packets to a
RAM-backed folder, and the workers tally, keep whole photons and image their slices while MCX runs
the next batch.  (On 27 Nov 2026 the parent still tallied and drew the whole photons itself: 37 s
of every 49-s batch on an H200 with 16 cores, so 1.1e9 photons in two 5-minute runs.)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))
import mcx_reference as MR  # noqa: E402

CARRY = ROOT / ".gpu21"  # what the GPU machine needs besides the repository (ignored by git)
SCENES = CARRY / "scenes.pkl"
EXPERIMENTS = ("direct", "mirrors", "direct-control")
ORIGIN_MM = np.array(MR.SIZE_MM, float) / 2  # MCX's grid corner -> the box's centre (fluxmap's own frame)


# ----------------------------------------------------------------------------- here: prepare
def prepare(names) -> None:
    """Pickle, per experiment, what imaging needs: views, placements, occluder meshes per pose,
    the truth's fine surface, the body's shape, the ray offset, the control's redraw table."""
    import issue21_box as B
    from diag_mc import mc_scenes

    from fluxcli.config import load_config
    from fluxcli.optics.emission import diffuse
    from fluxcli.scene import poses_from_config
    from fluxcli.surface.mesh import merge
    from fluxcli.truth import truth_refinement

    out = {}
    for name in names:
        cfg = load_config(B.configs(f"mcx-{name}")["diffuse"])
        m, shape, placer, views, scenes, placements, _ = mc_scenes(cfg)
        fine, parent = placer.own_surface.refined(truth_refinement(m.simulate))
        out[name] = {
            "views": views, "placements": placements, "rest_shift_mm": np.asarray(placer.rest_shift_mm, float),
            "occluders": [merge(s.surface, *s.occluders) for s in scenes], "shape": shape,
            "fine": (fine.vertices_mm, fine.faces, fine.element_of_face, fine.n_elements), "parent": parent,
            "ray_offset_mm": m.transfer.ray_offset_mm,
            "redraw": diffuse(B.N_INDEX).table if name.endswith("-control") else None,
            "poses": [str(p) for p in poses_from_config(m.subject)],
        }
        assert np.allclose(shape.half_mm, ORIGIN_MM), "the MCX grid and the box must agree"
    CARRY.mkdir(exist_ok=True)
    tmp = SCENES.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(out))
    tmp.replace(SCENES)
    print(f"wrote {SCENES} ({SCENES.stat().st_size / 1e6:.1f} MB): " + ", ".join(
        f"{k}: {len(v['placements'])} poses x {len(v['views'])} views" for k, v in out.items()))
    print("wheels for the GPU machine (python 3.12): python3 -m pip download --no-deps --only-binary=:all: "
          "--python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 --platform "
          f"manylinux_2_17_x86_64 -d {CARRY}/whl pmcx==0.8.1 embreex==4.4.0.post1")


# ----------------------------------------------------------------------------- GPU machine: workers
# A pool of worker processes, forked once before MCX or Embree start in the parent; each loads
# the scenes itself and reads its slice of a batch from files in a RAM-backed folder.
_EXP: dict = {}


def _init_worker(scenes_path: str) -> None:
    import issue21_box as B
    from fluxcli.optics.raycast import OcclusionScene
    exps = pickle.loads(Path(scenes_path).read_bytes())
    fines = {}
    for e in exps.values():
        e["occl"] = [OcclusionScene(v, f) for v, f in e["occluders"]]
        e["cones"] = B.reach_cones(e["views"], e["placements"], e["rest_shift_mm"],
                                   float(np.linalg.norm(e["shape"].half_mm)))
        key = hash((e["fine"][0].tobytes(), e["fine"][1].tobytes()))
        if key not in fines:
            fines[key] = OcclusionScene(e["fine"][0], e["fine"][1])
        e["fine_scene"], e["fine_key"] = fines[key], key
    _EXP.update(exps)


class _Fine:
    def __init__(self, vertices_mm, faces, element_of_face, n_elements):
        self.vertices_mm, self.faces = vertices_mm, faces
        self.element_of_face, self.n_elements = element_of_face, n_elements


def _work(job):
    """One slice [a, b) of a batch's detected packets: the top face's exit-angle tally, the
    packets kept as whole photons (Russian roulette), their exit bands per face, and their
    truth, images and photons at each lens (own frame).  All of it here, in a worker, so that
    the parent only runs MCX: done in the parent, the tally and the roulette took 37 s of every
    1e8-photon batch (MCX 7.5 s on an H200), and 16 workers waited for it."""
    import issue21_box as B
    from fluxcli.montecarlo import photons as MC_ph

    folder, a, b, batch, seed, with_tally = job
    det = np.array(np.load(Path(folder) / "det.npy", mmap_mode="r")[1:, a:b])  # row 0: MCX's detector id
    tally = MR.Tally(5.0)
    if with_tally:
        tally.add(det, None, 0, check=False)
    pos32, d32 = _whole_photons(det, np.random.default_rng([2026, seed, batch, a]))
    del det
    face_bands = B.face_band_counts(pos32, d32)
    pos, d = pos32.astype(np.float64), d32.astype(np.float64)
    d /= np.linalg.norm(d, axis=1)[:, None]
    shape = next(iter(_EXP.values()))["shape"]
    normal = shape.outward_normals(pos)
    out, truths = {}, {}
    for name, e in _EXP.items():
        if e["fine_key"] not in truths:
            truths[e["fine_key"]] = B.photon_truth(_Fine(*e["fine"]), e["fine_scene"], shape, pos)
        dd = d
        if e["redraw"] is not None:
            dd = MC_ph.redraw_directions(normal, e["redraw"], np.random.default_rng([11, batch, a]))
        img, got = B.image_posed(e["views"], e["occl"], e["placements"], e["rest_shift_mm"], e["cones"], pos, dd,
                                 normal, (7, batch, a), e["ray_offset_mm"])
        out[name] = (img, got, truths[e["fine_key"]])
    return out, tally, face_bands, len(pos)


# ----------------------------------------------------------------------------- GPU machine: transport
def _load_mcx(backend: str):
    if backend == "pmcxcl":
        return MR.load_pmcxcl()
    import pmcx
    return pmcx


def _whole_photons(det: np.ndarray, rng: np.random.Generator):
    """Exit points (own frame, float32) and directions of the packets kept as whole photons:
    each with probability w0 exp(-μa L)."""
    w = det[7] * np.exp(-MR.MU_A_PER_MM * det[0])
    keep = rng.random(w.size, dtype=np.float32) < w
    pos = (det[1:4, keep].T - ORIGIN_MM.astype(np.float32)).astype(np.float32)
    return np.ascontiguousarray(pos), np.ascontiguousarray(det[4:7, keep].T)


def _save(path: Path, acc: dict, meta: dict, tally, first_seed: int) -> None:
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, meta=json.dumps(meta), **{k: v for k, v in acc.items()})
    os.replace(tmp, path)
    if tally.n_launched:
        n = tally.n_launched
        MR.write_csv(path.with_name("mcx_box_n140_gpu.csv"), tally, [
            "MCX reference: exit-angle radiance at the top face of issue 21's turbid box",
            f"made by benchmarks/issue21_mcx.py transport on {meta['device']}",
            f"code: {meta['code']}; photons launched {n}; wall {meta['wall_s']:.0f} s",
            f"box {MR.SIZE_MM[0]}x{MR.SIZE_MM[1]}x{MR.SIZE_MM[2]} mm (1 mm voxels), mu_a {MR.MU_A_PER_MM} /mm, "
            f"mu_s {MR.MU_S_PER_MM} /mm, g {MR.G}, n {MR.N_MEDIUM} in air (isreflect=1, Fresnel at every face)",
            f"isotropic point source at {MR.SOURCE_MM} mm (grid corner at 0); settings as mcx_reference.py "
            f"(issrcfrom0=1 bc='______111111' savedetflag='dpxvw'); seeds from {first_seed}, one per MCX run",
            f"escaped fraction {tally.face_w.sum() / n:.5f}; L(0) fit up to {MR.FIT_MAX_DEG} deg; "
            f"top face >= {tally.edge_mm} mm from its edges; bands and L_rel as in mcx_reference.py"])


def _ram_folder() -> Path:
    import shutil
    for base in ("/dev/shm", "/tmp"):
        if Path(base).is_dir() and shutil.disk_usage(base).free > 8e9:
            return Path(base)
    return Path("/tmp")


def transport(photons: float, batch: float, seconds: float, out: Path, backend: str, workers: int,
              seed: int, with_tally: bool = True, split: float = 0) -> int:
    import issue21_box as B
    t_start = time.time()
    ctx = mp.get_context("fork")
    pool = ctx.Pool(workers, initializer=_init_worker, initargs=(str(SCENES),))  # before MCX and Embree start here
    folders = [_ram_folder() / f"issue21_mcx_{os.getpid()}_{i}" for i in range(2)]
    for f in folders:
        f.mkdir(exist_ok=True)
    exps = pickle.loads(SCENES.read_bytes())
    mcx = _load_mcx(backend)
    code = f"{backend} {mcx.version() if hasattr(mcx, 'version') else ''}".strip()
    try:
        info = mcx.gpuinfo()
        device = info[0]["name"] if info else "unknown"
    except Exception as exc:  # noqa: BLE001
        device = f"unknown ({exc})"
    print(f"[issue21_mcx] {code} on {device}; {workers} imaging workers; batches in {folders[0].parent}", flush=True)

    def empty() -> tuple[dict, dict]:
        acc: dict = {}
        for name, e in exps.items():
            P, V = len(e["placements"]), len(e["views"])
            cam = e["views"][0].camera
            acc[f"{name}/images"] = np.zeros((P, cam.nx * cam.ny), np.int64)
            acc[f"{name}/reached"] = np.zeros((P, V), np.int64)
            acc[f"{name}/fine_power"] = np.zeros(e["fine"][3], np.int64)
        # every whole photon's face and exit angle band (issue21_box.EXIT_EDGES_DEG): the profile per face
        acc["exit/face_bands"] = np.zeros((6, len(B.EXIT_EDGES_DEG) - 1), np.int64)
        meta = {"device": device, "code": code, "launched": 0, "whole_photons": 0, "batches": [], "wall_s": 0.0,
                "seed": seed + len(done_batches), "mcx_s": 0.0, "imaging_wait_s": 0.0}
        return acc, meta

    # with ``split``, every ``split`` photons launched close one part (its own file, ``<out>_p<k>.npz``):
    # independent realisations of a run of that size (their batches have their own seeds); summed by
    # ``reconstruct`` they are the whole run
    done_batches: list = []
    n_part = 0

    def part_path() -> Path:
        return out if not split else out.with_name(f"{out.stem}_p{n_part}{out.suffix}")

    acc, meta = empty()
    tally = MR.Tally(5.0)
    n_total, n_batch = int(photons), int(batch)
    pending = None  # (async result, photons launched, whole photons) of the batch being imaged

    def collect(p):
        nonlocal acc, meta, n_part
        res, n_launched, stat, record = p
        t = time.time()
        n_whole = 0
        for part, part_tally, face_bands, n in res.get():
            acc["exit/face_bands"] += face_bands
            tally.merge(part_tally)
            n_whole += n
            for name, (img, got, fine) in part.items():
                acc[f"{name}/images"] += img
                acc[f"{name}/reached"] += got
                acc[f"{name}/fine_power"] += fine
        tally.add_run(stat, n_launched if with_tally else 0)
        tally.check()
        record["whole"] = n_whole
        meta["imaging_wait_s"] += time.time() - t
        meta["launched"] += n_launched
        meta["whole_photons"] += n_whole
        meta["wall_s"] = time.time() - t_start
        _save(part_path(), acc, meta, tally, seed)  # what is imaged so far survives a stop
        print(f"[issue21_mcx] batch of seed {record['seed']}: {n_whole} whole photons escaped and imaged; "
              f"{time.time() - t_start:.0f} s", flush=True)
        if split and meta["launched"] >= split:
            done_batches.extend(meta["batches"])
            print(f"[issue21_mcx] part {n_part}: {meta['launched']:.4g} photons -> {part_path()}", flush=True)
            n_part += 1
            acc, meta = empty()

    b = launched_mcx = 0
    t_last = t_start  # when the last batch began: the first batch's MCX also compiles its kernel
    try:
        while launched_mcx < n_total:
            elapsed, last_s = time.time() - t_start, time.time() - t_last
            t_last = time.time()
            if b and elapsed + 1.5 * (last_s if b > 1 else elapsed) > seconds:
                print(f"[issue21_mcx] time budget: no batch after {launched_mcx:.3g} photons", flush=True)
                break
            n = min(n_batch, n_total - launched_mcx)
            t = time.time()
            det, stat = MR.run_chunk_raw(mcx, n, seed + b, dtype=np.float32)
            t_mcx = time.time() - t
            folder = folders[b % 2]
            if pending is not None:
                collect(pending)  # the other folder's batch is done before this one is overwritten
            meta["mcx_s"] += t_mcx  # (after collect, which may have closed a part)
            t = time.time()
            # whole, in MCX's own order: a strided view took 26-31 s per 1e8 packets to write on the
            # H100 machine (MCX itself 9 s)
            np.save(folder / "det.npy", det if det.flags.c_contiguous or det.flags.f_contiguous
                    else np.ascontiguousarray(det))
            t_save = time.time() - t
            n_det = det.shape[1]
            del det
            record = {"seed": seed + b, "launched": n, "whole": None, "mcx_s": round(t_mcx, 2),
                      "energy_escaped": float(stat["energytot"]) - float(stat["energyabs"])}
            meta["batches"].append(record)
            edges = np.linspace(0, n_det, 4 * workers + 1).astype(int)
            jobs = [(str(folder), int(x), int(y), b, seed, with_tally) for x, y in zip(edges[:-1], edges[1:])]
            pending = (pool.map_async(_work, jobs), n, stat, record)
            launched_mcx += n
            b += 1
            print(f"[issue21_mcx] batch {b}: {n:.3g} photons, {t_mcx:.1f} s of MCX, {t_save:.1f} s to hand over, "
                  f"{n_det} packets detected; "
                  f"{time.time() - t_start:.0f} s", flush=True)
        if pending is not None:
            collect(pending)
    finally:
        pool.terminate()
        for f in folders:
            for x in f.glob("*.npy"):
                x.unlink()
            f.rmdir()
    meta["wall_s"] = time.time() - t_start
    if meta["launched"]:
        _save(part_path(), acc, meta, tally, seed)
    n_all = meta["launched"] + sum(x["launched"] for x in done_batches)
    last = part_path() if meta["launched"] or not split else out.with_name(f"{out.stem}_p{n_part - 1}{out.suffix}")
    print(f"[issue21_mcx] done: {n_all:.4g} photons launched in {n_part + (meta['launched'] > 0)} part(s), "
          f"{time.time() - t_start:.0f} s wall; the last part -> {last}", flush=True)
    for name in exps:
        print(f"  {name}: photons per pose of the last part {acc[f'{name}/images'].sum(axis=1).tolist()}")
    return 0


# ----------------------------------------------------------------------------- here: reconstruct
def load_runs(paths) -> tuple[dict, dict]:
    """The sums of one or more transport runs (independent seeds) and their merged description."""
    acc, meta = {}, None
    for path in paths:
        with np.load(path) as z:
            m = json.loads(str(z["meta"]))
            for k in z.files:
                if k != "meta":
                    acc[k] = acc.get(k, 0) + z[k]
        if meta is None:
            meta = {**m, "seeds": [m["seed"]], "runs": 1, "by": {}}
        else:
            for k in ("launched", "whole_photons", "mcx_s", "wall_s"):
                meta[k] += m[k]
            meta["batches"] += m["batches"]
            meta["seeds"].append(m["seed"])
            meta["runs"] += 1
        who = f"{m['code']} on {m['device']}"
        meta["by"][who] = meta["by"].get(who, 0) + m["launched"]
    # every run's code and device, with its photons (runs by other codes or devices are summed too)
    meta["source"] = ", ".join(f"{who} ({n:.3g} photons)" for who, n in meta["by"].items())
    return acc, meta


def _holds(path: Path, key: str) -> bool:
    with np.load(path) as z:
        return key in z.files


def reconstruct(npzs, names) -> int:
    import issue21_box as B
    from diag_mc import mc_scenes

    from fluxcli.config import load_config
    from fluxcli.truth import truth_refinement

    ok = True
    for name in names:
        # only the runs that imaged this experiment (a run may have imaged only some of them)
        runs = [p for p in npzs if _holds(p, f"{name}/images")]
        if not runs:
            print(f"mcx-{name}: no run imaged it; skipped")
            ok = False
            continue
        z, meta = load_runs(runs)
        print(f"{meta['launched']:.4g} photons launched by {meta['source']} in {meta['runs']} run(s) "
              f"(first seeds {meta['seeds']}, {len(meta['batches'])} batches); {meta['whole_photons']:.4g} left the "
              f"box as whole photons; {meta['mcx_s']:.0f} s in MCX, {meta['wall_s']:.0f} s wall with imaging")
        tag = f"mcx-{name}"
        paths = B.configs(tag)
        t0 = time.perf_counter()
        sim = B.simulation_frame(tag, paths)
        m, shape, placer, views, scenes, placements, _ = mc_scenes(load_config(paths["diffuse"]))
        fine, parent = placer.own_surface.refined(truth_refinement(m.simulate))
        images = z[f"{name}/images"]
        B.store_photon_images(sim, placer.surface.element_areas_mm2, views[0].camera, images, z[f"{name}/reached"],
                              z[f"{name}/fine_power"].astype(float), parent, meta["launched"],
                              meta["whole_photons"], f"MCX: {meta['source']}, first seeds "
                              f"{meta['seeds']}, {len(meta['batches'])} batches")
        header = (f"{tag}: {meta['launched']:.3g} photons launched by {meta['source']} "
                  f"({meta['whole_photons']:.3g} left as whole photons), heights {B.AM.HEIGHTS[tag]} mm"
                  + ("; directions redrawn from diffuse(1.40), reconstructed with its profile alone (the control)"
                     if name.endswith("-control") else ""))
        ok &= B.reconstruct_models(tag, paths, sim, images.sum(axis=1), header, t0)
    return 0 if ok else 1


def bands(npzs) -> int:
    """The whole photons per face of the box by exit angle, over what diffuse(1.40) puts there
    (the runs that tallied them)."""
    import issue21_box as B
    runs = [p for p in npzs if _holds(p, "exit/face_bands")]
    if not runs:
        print("no run tallied the exit angles per face (runs from before 26 November 2026 did not)")
        return 1
    z, meta = load_runs(runs)
    print(f"{meta['launched']:.4g} photons launched by {meta['source']} in {meta['runs']} run(s), "
          f"{int(z['exit/face_bands'].sum()):.4g} whole photons left the box")
    B.print_face_bands(z["exit/face_bands"])
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="step", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--experiments", default=",".join(EXPERIMENTS))
    t = sub.add_parser("transport")
    t.add_argument("--photons", type=float, default=2e9)
    t.add_argument("--batch", type=float, default=1e8, help="photons per MCX run")
    t.add_argument("--seconds", type=float, default=420, help="launch no batch that would end past this")
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--backend", choices=("pmcx", "pmcxcl"), default="pmcx")
    t.add_argument("--workers", type=int, default=os.cpu_count())
    t.add_argument("--seed", type=int, default=21000)
    t.add_argument("--no-tally", action="store_true", help="skip the top face's exit-angle radiance")
    t.add_argument("--split", type=float, default=0,
                   help="close a part (its own file) every this many photons launched: independent runs of that size")
    r = sub.add_parser("reconstruct")
    r.add_argument("npz", type=Path, nargs="+", help="transport outputs (independent seeds), summed")
    r.add_argument("--experiments", default=",".join(EXPERIMENTS))
    b = sub.add_parser("bands", help="the whole photons' exit angles per face against diffuse(1.40)")
    b.add_argument("npz", type=Path, nargs="+")
    a = ap.parse_args(argv)
    if a.step == "prepare":
        prepare(a.experiments.split(","))
        return 0
    if a.step == "transport":
        a.out.parent.mkdir(parents=True, exist_ok=True)
        return transport(a.photons, a.batch, a.seconds, a.out, a.backend, a.workers, a.seed, not a.no_tally,
                         a.split)
    if a.step == "bands":
        return bands(a.npz)
    return reconstruct(a.npz, a.experiments.split(","))


if __name__ == "__main__":
    sys.exit(main())
