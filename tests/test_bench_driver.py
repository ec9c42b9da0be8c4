"""`make bench`'s driver: modules with run(repeats) -> rows, one table, one JSON with the machine."""

from __future__ import annotations

import json
import sys

from repo_scripts import load_script


def _driver():
    return load_script("benchmarks/run.py")


def test_driver_tables_rows_and_writes_json_with_the_machine(tmp_path, monkeypatch, capsys):
    (tmp_path / "fake_bench.py").write_text(
        "def run(repeats=3):\n"
        "    from run import row\n"
        "    return [row('4', 'a figure', 's', [3.0, 1.0, 2.0][:repeats], '<= 2 s', True, note='n', profile='p')]\n")
    (tmp_path / "broken_bench.py").write_text("def run(repeats=3):\n    raise RuntimeError('boom')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    drv = _driver()
    monkeypatch.setitem(sys.modules, "run", drv)
    out = tmp_path / "bench.json"
    code = drv.main(["--repeats", "3", "--only", "fake_bench", "broken_bench", "--out", str(out)])
    assert code == 1  # a failing module is a row and a non-zero exit, after the others ran
    text = capsys.readouterr().out
    assert "a figure" in text and "broken_bench failed" in text and "profile [4] a figure" in text
    data = json.loads(out.read_text())
    first = data["rows"][0]
    assert (first["min"], first["median"]) == (1.0, 2.0)
    assert {"item", "name", "unit", "min", "median", "target", "met", "note"} <= first.keys()
    m = data["machine"]
    assert m["cores"] >= 1 and m["cpu_model"] and len(m["load_average_start"]) == 3 and len(m["load_average_end"]) == 3
    assert m["versions"]["numpy"]
