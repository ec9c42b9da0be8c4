"""``--scheduler``: a sweep on a real Dask cluster (``distributed.LocalCluster``, worker
processes) makes the same bytes as the local run; progress moves; a bad address is exit 2."""

from __future__ import annotations

import hashlib
import shutil
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
    _run_all(cfg, ["--scheduler", cluster.scheduler_address])
    remote = _digests(tmp_path)
    local = {k.replace("local-", ""): v for k, v in _digests(tmp_path).items() if k.startswith("local-")}
    remote = {k: v for k, v in remote.items() if not k.startswith("local-")}
    assert remote.keys() == local.keys()
    assert remote == local  # every artefact and every cached T: the same bytes
    assert seen and max(f for _, f in seen) == 1.0 and min(f for _, f in seen) < 1.0
    with __import__("h5py").File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f["sweep/error"].shape[0] == 2 and f["sweep/error"].shape[-1] == 3  # the repeats ran remotely


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
