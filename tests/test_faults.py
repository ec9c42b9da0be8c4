"""Faults: a SIGKILLed or SIGTERMed build-T leaves no worker running, no temporary file
behind, and a rerun gives the T of a clean run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from fluxcli.artefacts import atomic_path, clean_stale_temps
from fluxcli.artefacts.atomic import host_tag
from fluxcli.artefacts.transfer import load_T

from conftest import cylinder_sim_config

FLUXMAP = [sys.executable, "-m", "fluxcli.cli"]


def _children(pid: int) -> set[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            kids.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")  # a zombie has stopped running


def _config(tmp_path: Path, minimal_config: dict, workdir: str) -> Path:
    cfg = cylinder_sim_config(minimal_config)
    cfg["workdir"] = workdir
    cfg["system"]["camera"]["pixels"] = [64, 64]
    # long enough (~4 s with --jobs 2 on an idle 2-core machine) that the signal always lands
    # while the workers compute: a build that ends first would make the test race the machine
    # (2048 lens samples: the compiled T kernel casts ~4x faster than the numpy path did at 512)
    cfg["subject"]["poses"] = {"heights_mm": [0, 2, 4, 6, 8, 10, 12, 14]}
    cfg["transfer"] = {"lens": {"surface_samples_per_pixel": 4, "lens_samples_min": 2048}}
    p = tmp_path / f"{workdir}.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def _start_and_signal(cfg: Path, cache: Path, sig: int, *, group: bool = False):
    """Run build-T --jobs 2, send ``sig`` while both workers compute (or one writes a T);
    returns the process, the workers seen, and seconds from the signal to the parent's exit."""
    proc = subprocess.Popen([*FLUXMAP, "build-T", str(cfg), "--jobs", "2", "-q"], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers: set[int] = set()
    t_start = time.monotonic()
    while time.monotonic() < t_start + 30:  # mid-pose: both workers exist; mid-write if a T temp file shows
        workers |= _children(proc.pid)
        writing = cache.is_dir() and any(p.name.endswith(".tmp.h5") for p in cache.iterdir())
        if len(workers) >= 2 and (writing or time.monotonic() > t_start + 1.0):
            break
        time.sleep(0.01)
    assert len(workers) >= 2 and proc.poll() is None, proc.stderr.read()
    t0 = time.monotonic()
    if group:
        os.killpg(proc.pid, sig)  # what Ctrl-C in a terminal does: the whole foreground group
    else:
        os.kill(proc.pid, sig)
    proc.wait(timeout=10)
    return proc, workers, time.monotonic() - t0


def _wait_gone(pids: set[int], seconds: float = 5.0) -> list[int]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.05)
    return [p for p in pids if _alive(p)]


def test_SIGKILLed_build_T_leaves_no_workers_no_temp_files_and_a_rerun_gives_the_clean_T(tmp_path, minimal_config):
    clean = _config(tmp_path, minimal_config, "clean")
    assert subprocess.run([*FLUXMAP, "build-T", str(clean), "-q"], capture_output=True).returncode == 0
    cfg = _config(tmp_path, minimal_config, "killed")
    cache = tmp_path / "killed" / "cache" / "T"
    proc, workers, _ = _start_and_signal(cfg, cache, signal.SIGKILL)
    assert not _wait_gone(workers), "workers outlived their SIGKILLed parent by 5 s"
    # besides whatever the kill left, the exact file a writer killed mid-write leaves (its pid is dead)
    cache.mkdir(parents=True, exist_ok=True)
    (cache / f".{'0' * 64}.h5.{host_tag()}.{max(workers)}.0123abcd.tmp.h5").write_bytes(b"\0" * 4096)
    r = subprocess.run([*FLUXMAP, "build-T", str(cfg), "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert not [p for p in cache.iterdir() if ".tmp" in p.name], list(cache.iterdir())
    ref = sorted((tmp_path / "clean" / "cache" / "T").glob("*.h5"))
    got = sorted(cache.glob("*.h5"))
    assert [p.name for p in ref] == [p.name for p in got] and len(got) == 8
    for a, b in zip(ref, got):
        Ta, Tb = load_T(a), load_T(b)
        assert Ta.shape == Tb.shape and (Ta != Tb).nnz == 0


@pytest.mark.parametrize("sig, code, group", [(signal.SIGTERM, 143, False), (signal.SIGINT, 130, True)])
def test_SIGTERM_and_ctrl_c_stop_build_T_within_2_s_and_kill_the_workers(tmp_path, minimal_config, sig, code, group):
    cfg = _config(tmp_path, minimal_config, "run")
    cache = tmp_path / "run" / "cache" / "T"
    proc, workers, seconds = _start_and_signal(cfg, cache, sig, group=group)
    err = proc.stderr.read()
    assert proc.returncode == code, f"exit {proc.returncode} after {seconds:.2f} s: {err}"
    assert seconds < 2.0, f"took {seconds:.1f} s to stop"
    assert "Traceback" not in err and ("stopping" in err if sig == signal.SIGINT else "terminated" in err)
    assert not _wait_gone(workers, 3.0)
    assert not [p for p in cache.iterdir() if ".tmp" in p.name] if cache.is_dir() else True


def test_temp_files_of_live_writers_are_kept_and_dead_ones_removed(tmp_path):
    live = tmp_path / f".x.h5.{host_tag()}.{os.getpid()}.0123abcd.tmp.h5"
    dead_pid = 2 ** 22 + 12345  # above the default pid_max of most systems: no such process
    dead = tmp_path / f".x.h5.{host_tag()}.{dead_pid}.0123abcd.tmp.h5"
    elsewhere = tmp_path / f".x.h5.another-machine.{dead_pid}.0123abcd.tmp.h5"  # its pids are not ours to judge
    for p in (live, dead, elsewhere):
        p.write_bytes(b"x")
    assert clean_stale_temps(tmp_path) == [dead]
    assert live.exists() and not dead.exists() and elsewhere.exists()


def test_atomic_writes_honour_the_umask_and_leave_nothing_on_failure(tmp_path):
    old = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("hello")
        assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
        os.umask(0o002)
        with atomic_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("hello")
        assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o664
        with pytest.raises(RuntimeError):
            with atomic_path(tmp_path / "c.txt") as tmp:
                tmp.write_text("half")
                raise RuntimeError("killed")
    finally:
        os.umask(old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
