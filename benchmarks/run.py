"""``make bench``: every benchmark module, one table, one JSON file.

Run: make bench   (or .venv/bin/python benchmarks/run.py [--repeats 3] [--only bench_inverse ...])

Each module ``benchmarks/bench_*.py`` in :data:`MODULES` exposes ``run(repeats: int = 3) ->
list[dict]``, one dict per figure::

    {"item": "4", "name": "...", "unit": "s", "min": 0.8, "median": 0.9,
     "target": "<= 1 s" | None, "met": True | False | None, "note": "...", "profile": "..." (optional)}

``min``/``median`` are over ``repeats`` runs; figures the issue asks as ratios are ratios
measured within this one run (machines are shared and noisy: absolute seconds are
contended). The driver prints one table (item, name, min, median, unit, target, met), then
the profiles, and writes ``runs/bench/bench.json`` with the machine (cores, CPU model, load
average at start and end, versions). A module that fails gives a row saying so and the
driver exits 1 after the others ran.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import subprocess
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

# item 1-3: the T kernel (bench_transfer); item 4: reconstruction, diffusion, Dask
MODULES = ["bench_transfer", "bench_inverse", "bench_diffusion", "bench_dask", "bench_scale", "bench_montecarlo"]
KEYS = ("item", "name", "unit", "min", "median", "target", "met", "note")


def row(item: str, name: str, unit: str, values, target: str | None = None, met: bool | None = None,
        note: str = "", profile: str | None = None) -> dict:
    """One figure: min and median over its repeats."""
    import statistics

    values = [float(v) for v in values]
    d = {"item": item, "name": name, "unit": unit, "min": min(values), "median": statistics.median(values),
         "target": target, "met": met, "note": note, "values": values}
    if profile:
        d["profile"] = profile
    return d


def _clean(x):
    """JSON without NaN (null instead)."""
    if isinstance(x, float) and x != x:
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for name in ("fluxmap", "numpy", "scipy", "embreex", "numba", "pyamg", "dask", "distributed", "h5py"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    try:
        out["git_commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                           timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        out["git_commit"] = None
    return out


def machine() -> dict:
    return {"cores": os.cpu_count(), "cpu_model": cpu_model(), "platform": platform.platform(),
            "memory_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9, 1),
            "load_average_start": list(os.getloadavg()), "versions": versions()}


def run_module(name: str, repeats: int) -> tuple[list[dict], bool]:
    """The module's rows, and whether it ran cleanly."""
    t0 = time.perf_counter()
    try:
        mod = importlib.import_module(name)
        if hasattr(mod, "run"):
            rows = list(mod.run(repeats=repeats))
        else:  # an older module that only prints (bench_transfer before issue 14's items 1-3): run it as a script
            import runpy

            runpy.run_path(str(HERE / f"{name}.py"), run_name="__main__")
            rows = [{"item": "?", "name": f"{name}: printed above (no run())", "unit": "", "min": float("nan"),
                     "median": float("nan"), "target": None, "met": None,
                     "note": "module without the run(repeats) interface"}]
        ok = True
    except Exception:
        tb = traceback.format_exc()
        print(tb, file=sys.stderr)
        rows = [{"item": "?", "name": f"{name} failed", "unit": "", "min": float("nan"), "median": float("nan"),
                 "target": None, "met": False, "note": tb.strip().splitlines()[-1]}]
        ok = False
    for r in rows:
        r.setdefault("module", name)
        r.setdefault("note", "")
    print(f"[{name}: {time.perf_counter() - t0:.0f} s]", file=sys.stderr, flush=True)
    return rows, ok


def _num(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if x != x:
            return "-"
        return f"{x:.4g}"
    return str(x)


def table(rows: list[dict]) -> str:
    head = ["item", "name", "min", "median", "unit", "target", "met"]
    cells = [[str(r.get("item", "")), str(r.get("name", "")), _num(r.get("min")), _num(r.get("median")),
              str(r.get("unit", "")), str(r.get("target") or "-"),
              {True: "yes", False: "NO", None: "-"}[r.get("met")]] for r in rows]
    width = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(head)]
    line = lambda c: "  ".join(x.ljust(w) for x, w in zip(c, width)).rstrip()  # noqa: E731
    out = [line(head), line(["-" * w for w in width])] + [line(c) for c in cells]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="Repeats per figure (min and median over them).")
    ap.add_argument("--only", nargs="*", default=None, help=f"Modules to run (of {', '.join(MODULES)}).")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "bench.json")
    a = ap.parse_args(argv)
    info = machine()
    rows, ok = [], True
    for name in a.only or MODULES:
        r, good = run_module(name, a.repeats)
        rows += r
        ok &= good
    info["load_average_end"] = list(os.getloadavg())
    print()
    print(table(rows))
    notes = [f"  [{r['item']}] {r['name']}: {r['note']}" for r in rows if r.get("note")]
    if notes:
        print("\nnotes:")
        print("\n".join(notes))
    for r in rows:
        if r.get("profile"):
            print(f"\nprofile [{r['item']}] {r['name']}:\n{r['profile']}")
    print(f"\n{info['cores']} cores ({info['cpu_model']}), load average {info['load_average_start'][0]:.2f} at start, "
          f"{info['load_average_end'][0]:.2f} at end: absolute times are as contended as that; ratios are within one run.")
    from fluxcli.artefacts.atomic import write_text

    write_text(a.out, json.dumps(_clean({"machine": info, "repeats": a.repeats, "rows": rows}), indent=1, default=str))
    print(f"written: {a.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
