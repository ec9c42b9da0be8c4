"""Every key of a full config, set to each of a dozen hostile values, run through the stage
that reads it: exit 0 or exit 2 (a clear error), never 1 (a bug).  This found a length of
1e300 mm overflowing inside the ray tracer and n_angular = 10^7 filling 6 GB of memory.

~800 runs, a few minutes: `make bench` (pytest -m slow), not `make test`."""

from __future__ import annotations

import copy
import shutil

import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from tiny_pipeline import tiny_config

HOSTILE = [0, -1, float("nan"), "abc", [], {}, True, None, 1e300, [1, 2, 3, 4], 1e-9, 1e5, 2**31, -0.0]
STAGE = {"system": "build-T", "subject": "build-T", "transfer": "build-T", "simulate": "simulate",
         "reconstruct": "reconstruct", "report": "report"}


def leaves(node, path=()):
    """(path, value) of every scalar and of every list of scalars (and its items)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaves(v, path + (k,))
    elif isinstance(node, list) and node and not isinstance(node[0], (dict, list)):
        yield path, node
        for i, v in enumerate(node):
            yield path + (i,), v
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from leaves(v, path + (i,))
    else:
        yield path, node


@pytest.mark.slow
def test_no_hostile_value_of_any_key_is_a_bug(tmp_path):
    runner = CliRunner()
    cfg = tiny_config(tmp_path)
    cfg["system"]["mirrors"] = [{"name": "right", "center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1],
                                 "axis": [1, 0, 0], "size_mm": [70, 40]}]
    cfg["system"]["stage"] = {"top_z_mm": -9.0, "size_mm": [100, 34], "thickness_mm": 5}
    cfg["system"]["camera"]["apertures"] = [{"distance_mm": 30.0, "diameter_mm": 25.0}]
    cfg["report"] = {"title": "fuzz"}
    p = tmp_path / "c.yaml"

    def run(stage, c):
        p.write_text(yaml.safe_dump(c))
        return runner.invoke(app, [stage, str(p), "-q"])

    for stage in ("build-T", "simulate", "reconstruct", "report"):  # a good run to start each from
        r = run(stage, cfg)
        assert r.exit_code == 0, r.output
    bugs = []
    for path, _ in list(leaves(cfg)):
        if path[0] not in STAGE or path[-1] == "cache_dir":
            continue
        for value in HOSTILE:
            c = copy.deepcopy(cfg)
            node = c
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = value
            work = tmp_path / "work"
            shutil.rmtree(work, ignore_errors=True)
            shutil.copytree(tmp_path / "run", work)
            c["workdir"] = str(work)
            r = run(STAGE[path[0]], c)
            if r.exit_code not in (0, 2):
                bugs.append(f"{'.'.join(map(str, path))} = {value!r}: exit {r.exit_code}\n{r.output[-800:]}")
    assert not bugs, "\n\n".join(bugs)
