"""Item 4 (Dask): a small sweep (build-T, simulate, reconstruct with a sweep over noise
repeats) run locally with --jobs 2 and on a 2-worker ``distributed.LocalCluster``
(processes) in the same run: wall time of each, their ratio, and whether every artefact and
cached T came out byte-identical (SOURCE_DATE_EPOCH fixes creation times, as `make demo`).

Run: .venv/bin/python benchmarks/run.py --only bench_dask

On one 2-core machine the cluster cannot be faster than local processes; the figure is the
overhead of going through a scheduler, and the identity is the point.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def _config(base: Path) -> Path:
    from tiny_pipeline import tiny_config

    cfg = tiny_config(base)
    cfg["subject"]["poses"] = {"heights_mm": [0, 4, 8, 12]}
    cfg["simulate"]["noise"]["repeats"] = 4
    cfg["reconstruct"]["sweep"] = {"methods": [{"method": "nnls", "lambda": 0.0}, {"method": "backprojection"}]}
    p = base / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def _sweep(cfg: Path, extra: list[str]) -> float:
    from typer.testing import CliRunner

    from fluxcli.cli import app

    t = time.perf_counter()
    for stage in ("build-T", "simulate", "reconstruct"):
        r = CliRunner().invoke(app, [stage, str(cfg), "-q", *extra])
        if r.exit_code != 0:
            raise RuntimeError(f"{stage} {extra}: exit {r.exit_code}: {r.output}")
    return time.perf_counter() - t


def _digests(base: Path) -> dict[str, str]:
    return {str(p.relative_to(base)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(base.rglob("*.h5"))}


def run(repeats: int = 3) -> list[dict]:
    import distributed

    from run import row

    old = os.environ.get("SOURCE_DATE_EPOCH")
    os.environ["SOURCE_DATE_EPOCH"] = "1700000000"
    local_s, remote_s, same, differ = [], [], [], set()
    try:
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                      silence_logs=50) as cluster:
            for _ in range(repeats):
                with tempfile.TemporaryDirectory() as tmp:
                    base = Path(tmp)
                    cfg = _config(base)
                    local_s.append(_sweep(cfg, ["--jobs", "2"]))
                    local = _digests(base)
                    for d in ("run", "cache"):
                        shutil.rmtree(base / d)
                    remote_s.append(_sweep(cfg, ["--scheduler", cluster.scheduler_address]))
                    remote = _digests(base)
                    same.append(remote == local and len(local) > 0)
                    differ |= {k for k in set(local) | set(remote) if local.get(k) != remote.get(k)}
    finally:
        if old is None:
            os.environ.pop("SOURCE_DATE_EPOCH", None)
        else:
            os.environ["SOURCE_DATE_EPOCH"] = old
    n_files = len(local)
    return [
        row("4", "Dask sweep (4 poses, 4 repeats x 2 methods): local --jobs 2", "s", local_s),
        row("4", "Dask sweep: LocalCluster 2 workers (--scheduler)", "s", remote_s, note="contended machine"),
        row("4", "Dask sweep: time cluster / local (same run)", "x", [r / loc for r, loc in zip(remote_s, local_s)],
            note="one 2-core machine: the scheduler's overhead, not a speed-up"),
        row("4", f"Dask sweep: {n_files} artefacts + cached T byte-identical to the local run", "runs identical",
            [sum(same)], f"{repeats} of {repeats}", all(same),
            note=f"differing: {', '.join(sorted(differ))}" if differ else ""),
    ]


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    from run import main

    sys.exit(main(["--only", "bench_dask", *sys.argv[1:]]))
