"""``--scheduler``: a sweep on a real Dask cluster (``distributed.LocalCluster``, worker
processes) makes the same bytes as the local run; progress moves; a bad address is exit 2."""

from __future__ import annotations

import hashlib
import pickle
import shutil
import warnings
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.progress import run_tasks
from tiny_pipeline import tiny_config

EPOCH = "1700000000"


def _sweep_config(base: Path) -> Path:
    """The tiny two-pose cylinder, three noise repeats, a two-method sweep over them."""
    cfg = tiny_config(base)
    cfg["system"]["camera"] |= {"pixels": [48, 48], "pixel_pitch_mm": 0.05}  # T larger than a task's other data
    cfg["simulate"]["noise"]["repeats"] = 3
    cfg["transfer"]["lens"] = {"lens_samples_min": 8, "lens_samples_max": 64}  # small: the test is about the bytes
    cfg["simulate"]["transfer"] = {"lens": {"lens_samples_min": 16, "lens_samples_max": 128}}
    cfg["reconstruct"]["sweep"] = {"methods": [{"method": "nnls", "lambda": 0.0}, {"method": "backprojection"}]}
    p = base / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def _run_all(cfg: Path, extra: list[str]) -> None:
    for stage in ("build-T", "simulate", "reconstruct"):
        r = CliRunner().invoke(app, [stage, str(cfg), "-q", *extra])
        assert r.exit_code == 0, (stage, r.output)


def _digests(base: Path) -> dict[str, str]:
    return {str(p.relative_to(base)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(base.rglob("*.h5"))}


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50) as c:
        yield c


def test_sweep_on_a_local_cluster_is_byte_identical_to_the_local_run(tmp_path, monkeypatch, cluster):
    dask = pytest.importorskip("dask")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)  # creation times fixed, as `make demo` does
    cfg = _sweep_config(tmp_path)
    _run_all(cfg, ["--jobs", "2"])
    local = _digests(tmp_path)
    assert len([k for k in local if k.startswith("cache")]) >= 4, local  # T and forward T of both poses
    shutil.move(tmp_path / "run", tmp_path / "local-run")
    shutil.move(tmp_path / "cache", tmp_path / "local-cache")
    seen = []
    import fluxcli.cluster as FC

    real = FC._EventQueue.drain

    def spy(self):  # progress from the workers reaches this process
        for ev in real(self):
            seen.append(ev)
            yield ev

    monkeypatch.setattr(FC._EventQueue, "drain", spy)
    # no task carries a T: Dask warns about any graph larger than the smallest T (pickled)
    from fluxcli.artefacts.transfer import load_T

    smallest = min(len(pickle.dumps(load_T(p))) for p in (tmp_path / "local-cache").glob("*.h5"))
    with dask.config.set({"distributed.admin.large-graph-warning-threshold": smallest}):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _run_all(cfg, ["--scheduler", cluster.scheduler_address])
            from distributed import Client

            with Client(cluster.scheduler_address, set_as_default=False) as client:  # the check itself works
                client.submit(repr, load_T(next((tmp_path / "local-cache").glob("*.h5")))).result()
    large = [str(w.message) for w in caught if "large graph" in str(w.message)]
    assert len(large) == 1, ([m.splitlines()[0] for m in large], smallest)  # only the deliberate one
    remote = _digests(tmp_path)
    local = {k.replace("local-", ""): v for k, v in _digests(tmp_path).items() if k.startswith("local-")}
    remote = {k: v for k, v in remote.items() if not k.startswith("local-")}
    assert remote.keys() == local.keys()
    assert remote == local  # every artefact and every cached T: the same bytes
    assert seen and max(f for _, f in seen) == 1.0 and min(f for _, f in seen) < 1.0
    with __import__("h5py").File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f["sweep/error"].shape[0] == 2 and f["sweep/error"].shape[-1] == 3  # the repeats ran remotely


def _one_pose_config(base: Path) -> Path:
    """The tiny cylinder at one pose, cast in many small chunks (so one pose has blocks)."""
    cfg = tiny_config(base)
    cfg["subject"]["poses"] = {"heights_mm": [0]}
    cfg["transfer"]["rays_per_batch"] = 1000
    p = base / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def _build_T(cfg: Path, extra: list[str]) -> None:
    r = CliRunner().invoke(app, ["build-T", str(cfg), "-q", *extra])
    assert r.exit_code == 0, r.output


def _die_in_first_save(marker: str) -> None:
    """On a worker: the first block save anywhere (whichever worker gets there first) leaves a
    half-written temporary file beside the block and kills its worker process, as a machine
    lost mid-write would; the nanny starts a fresh worker and the scheduler runs the task again."""
    import os

    from fluxcli.transfer_cache.build import PartialFiles

    real = PartialFiles.save

    def save(self, view, spans, results):
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return real(self, view, spans, results)
        os.close(fd)
        from fluxcli.artefacts.atomic import temp_name

        self.folder.mkdir(parents=True, exist_ok=True)
        temp_name(self._path(view, spans)).write_bytes(b"PK\x03\x04 torn")
        os._exit(1)

    save.real = real
    PartialFiles.save = save


def _restore_save() -> None:
    from fluxcli.transfer_cache.build import PartialFiles

    PartialFiles.save = getattr(PartialFiles.save, "real", PartialFiles.save)  # the surviving worker's, as it was


def test_one_pose_is_split_into_blocks_on_the_cluster_and_merged_to_the_local_bytes(tmp_path, monkeypatch, cluster):
    """One pose on a 2-worker cluster: its lens build goes out as >= 3 block tasks (scene
    built on the workers), their partial files merge into the T the local build writes, byte
    for byte — also when a worker dies while writing a block (the task is run again)."""
    from distributed import Client

    import fluxcli.cluster as FC
    from fluxcli.transfer_cache import cluster as TC

    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    cfg = _one_pose_config(tmp_path)
    _build_T(cfg, ["--jobs", "2"])
    local = _digests(tmp_path)
    assert len(local) == 2  # the cached T and build-T's artefact
    for d in ("cache", "run"):
        shutil.rmtree(tmp_path / d)

    monkeypatch.setattr(TC, "CLUSTER_MIN_BLOCK_RAYS", 1)  # the tiny pose is ~1e5 rays
    tasks, seen = [], []
    real_run, real_drain = TC.run_tasks, FC._EventQueue.drain

    def spy_run(fn, arglists, **kw):
        tasks.extend([a[0].__name__ for a in arglists if a[0] is not TC._plan_view] if fn is TC._call
                     else [])
        return real_run(fn, arglists, **kw)

    def spy_drain(self):
        for ev in real_drain(self):
            seen.append(ev)
            yield ev

    monkeypatch.setattr(TC, "run_tasks", spy_run)
    monkeypatch.setattr(FC._EventQueue, "drain", spy_drain)
    _build_T(cfg, ["--scheduler", cluster.scheduler_address])
    assert len(tasks) >= 3 and set(tasks) == {"_build_block"}, tasks
    assert _digests(tmp_path) == local  # the merged T: the local bytes
    assert not list((tmp_path / "cache").glob("*.part"))  # the blocks are removed once merged
    assert len({t for t, _ in seen}) >= 3 and any(0 < f < 1 for _, f in seen)  # block tasks move the bar

    # a worker killed while writing a block: the task is run again elsewhere, nothing is corrupted
    for d in ("cache", "run"):
        shutil.rmtree(tmp_path / d)
    marker = tmp_path / "died"
    with Client(cluster.scheduler_address, set_as_default=False) as client:
        client.run(_die_in_first_save, str(marker))
        tasks.clear()
        _build_T(cfg, ["--scheduler", cluster.scheduler_address])
        assert marker.exists()  # a worker did die mid-write
        client.wait_for_workers(2, timeout=60)  # the nanny's fresh worker, for the next tests
        client.run(_restore_save)
    assert len(tasks) >= 3
    assert _digests(tmp_path) == local
    assert not list((tmp_path / "cache").glob("*.part")) and not list((tmp_path / "cache").glob(".*"))


def test_a_block_task_run_twice_writes_the_same_bytes_and_does_not_cast_again(tmp_path, monkeypatch):
    """Retry safety of one block task, in this process: the second run finds the file and
    leaves it as it is; a block cast anew (the file removed) makes the same bytes."""
    from fluxcli.config import load_config
    from fluxcli.optics.transfer import LensSampling, lens_blocks, lens_chunks, lens_plan
    from fluxcli.stages.plans import plan
    from fluxcli.transfer_cache import cluster as TC

    c = load_config(_one_pose_config(tmp_path))
    views, _, todo = plan(c)
    scene, pt = todo[0]
    tr = c.model.transfer
    plan = lens_plan(scene.surface, views[0], LensSampling(**tr.lens.model_dump()), tr.rays_per_batch)
    blocks = lens_blocks(*lens_chunks(plan), plan.rays // 3)
    assert len(blocks) >= 3
    scene_file = TC.PartialFiles(pt.path.parent, pt.path.stem).save_scene(scene)
    TC._build_block(scene_file, views, tr, pt.path, 0, blocks[1], plan.rays // 3)
    (part,) = pt.path.parent.glob("*.part/view*.npz")
    first = part.read_bytes()
    casts = []
    monkeypatch.setattr(TC, "cast_lens_block", lambda *a, **k: casts.append(1))
    TC._build_block(scene_file, views, tr, pt.path, 0, blocks[1], plan.rays // 3)
    assert casts == [] and part.read_bytes() == first
    monkeypatch.undo()
    TC._worker_scenes.clear()  # as on a fresh worker: scene and plan made again
    part.unlink()
    TC._build_block(scene_file, views, tr, pt.path, 0, blocks[1], plan.rays // 3)
    assert part.read_bytes() == first


def test_collection_efficiency_has_the_same_bits_with_any_number_of_blas_threads():
    """A Dask worker runs with one BLAS thread, this process with several: build-T's index
    (efficiency per view) must not depend on it (a BLAS dot over 20 000 elements did)."""
    import math

    import numpy as np
    import scipy.sparse as sp
    from threadpoolctl import threadpool_limits

    from fluxcli.artefacts.transfer import efficiency

    rng = np.random.default_rng(3)
    T = sp.random(4000, 20_000, density=1e-3, random_state=rng, format="csr")
    areas = rng.uniform(0.5, 2.0, 20_000)
    got = []
    for n in (1, 2):
        with threadpool_limits(n):
            got.append(efficiency(T, 0.9, areas))
    assert got[0] == got[1]
    col = np.asarray(T.sum(axis=0)).ravel() * 0.9
    assert math.isclose(got[0], math.fsum(col * areas) / math.fsum(areas), rel_tol=1e-12)


def _fails_once(marker, x, progress=None):
    """Fails the first time (a lost worker), then succeeds: the scheduler's retry."""
    p = Path(marker)
    if not p.exists():
        p.write_text("failed once")
        raise RuntimeError("worker lost")
    progress(0.5)
    return x + 1


def test_a_failed_task_is_retried_on_the_cluster(tmp_path, cluster):
    from distributed import Client

    from fluxcli.workers import pool_for

    with Client(cluster.scheduler_address, set_as_default=False) as client:
        out = run_tasks(_fails_once, [(str(tmp_path / "m"), 1)], label="t", quiet=True, remote=True,
                        pool=pool_for(client))
    assert out == [2]


def test_an_unreachable_scheduler_is_exit_2_naming_it(tmp_path, monkeypatch):
    import fluxcli.cluster as FC

    monkeypatch.setattr(FC, "CONNECT_TIMEOUT_S", 1.0)
    cfg = _sweep_config(tmp_path)
    r = CliRunner().invoke(app, ["build-T", str(cfg), "--scheduler", "tcp://127.0.0.1:9"])
    assert r.exit_code == 2, r.output
    assert "tcp://127.0.0.1:9" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.h5"))


def test_ctrl_c_cancels_a_build_on_the_cluster(tmp_path, cluster):
    """SIGINT to fluxmap while the cluster builds: exit 130 within seconds, no traceback,
    and the tasks not yet finished are cancelled on the scheduler."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from distributed import Client

    cfg = tiny_config(tmp_path)
    cfg["subject"]["poses"] = {"heights_mm": [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]}
    cfg["transfer"]["lens"] = {"lens_samples_min": 2048, "lens_samples_max": 2048}  # seconds per pose
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    proc = subprocess.Popen([sys.executable, "-m", "fluxcli.cli", "build-T", str(p), "--scheduler",
                             cluster.scheduler_address], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=os.environ | {"COLUMNS": "120"})
    with Client(cluster.scheduler_address, set_as_default=False) as client:
        t_end = time.monotonic() + 60
        while not any(client.processing().values()) and time.monotonic() < t_end:  # tasks reached the workers
            time.sleep(0.1)
        assert proc.poll() is None, proc.communicate()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        stopped_s = time.monotonic() - t0
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "interrupted" in err
        assert stopped_s < 10.0, f"took {stopped_s:.1f} s to stop"
        t_end = time.monotonic() + 30  # what was queued is cancelled (what runs finishes on its own)
        while client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) and time.monotonic() < t_end:
            time.sleep(0.2)
        assert client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0
    assert len(list((tmp_path / "cache").rglob("*.h5"))) < 10  # the queued poses were never built
