"""``make study``: a simulated study, from sessions to the study table and page (issue 24).

Two subjects, each imaged on days 3, 7 and 10 with a growing source (brighter and wider
each day), in two poses per session (turned 0° and −60°) and through two emission
filters (each passing its share of the source's light; reconstructed filter by filter, one
run each).  Every session is build-T → simulate → reconstruct of ``configs/study.yaml``
with the day's source; then ``fluxmap study`` makes ``runs/study/out/study.csv`` and its
page.  Checked, and printed:

- each subject's ROI total, joint over the poses, follows the true growth (the total on
  day d over day 3) within 2 %, per filter;
- the photons summed over the direct view's pixels (the number image-ROI tools give) swing
  from one pose to the other;
- a study that adds a session made with another camera calibration (a refitted focal
  length) is flagged, naming the difference;
- a study whose artefact was changed after it was written is refused (exit 2), naming it;
- the study page opens in headless Chromium without console errors (skipped, and said so,
  when no Chromium is installed).

$ python pipelines/study.py          # what `make study` runs (about 3 minutes on 2 cores)
"""

from __future__ import annotations

import copy
import csv
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs" / "study"
FLUXMAP = str(Path(sys.executable).parent / "fluxmap")
DAYS = (3, 7, 10)
# the source on each day: (peak photons per exposure of the brightest element, width mm)
GROWTH = {"m1": ((1.2e8, 2.5), (2e8, 3.0), (3.2e8, 3.5)), "m2": ((1.6e8, 3.0), (1.84e8, 3.2), (2.2e8, 3.5))}
CENTRE = {"m1": (5.0, 0.0, 25.0), "m2": (-9.0, 6.25, 23.3)}  # on the cylinder's surface, at rest
FILTERS = {"F520": 0.55, "F620": 0.30}  # the share of the source's light each filter passes
GROWTH_TOL = 0.02


def session_config(base: dict, subject: str, day_index: int, filt: str, workdir: Path, *, focal_mm=None) -> dict:
    cfg = copy.deepcopy(base)
    peak, width = GROWTH[subject][day_index]
    cfg["workdir"] = str(workdir)
    cfg["transfer"]["cache_dir"] = str(RUNS / "cache")
    cfg["simulate"]["flux"].update(center_mm=list(CENTRE[subject]), width_mm=width, peak_photons=peak * FILTERS[filt])
    cfg["simulate"]["noise"]["seed"] = 100 * day_index + len(filt) + (0 if subject == "m1" else 50)
    cfg["rois"][0]["center_mm"] = list(CENTRE[subject])
    if focal_mm is not None:  # a second calibration of the camera: another focal length
        cfg["system"]["camera"]["lens"]["focal_length_mm"] = focal_mm
    return cfg


def run_session(cfg: dict, name: str) -> Path:
    d = Path(cfg["workdir"])
    d.mkdir(parents=True, exist_ok=True)
    p = d / "session.yaml"
    p.write_text(yaml.safe_dump(cfg, sort_keys=False))
    for stage in ("build-T", "simulate", "reconstruct"):
        r = subprocess.run([FLUXMAP, stage, str(p), "-q"], capture_output=True, text=True)
        if r.returncode != 0:
            sys.exit(f"study: {stage} of session {name} failed:\n{r.stdout}{r.stderr}")
    return d / "reconstruction.h5"


def study_file(path: Path, sessions: list[dict], title: str) -> Path:
    path.write_text(yaml.safe_dump({"title": title, "output": f"out/{path.stem}", "rois": ["tumour", "contour50"],
                                    "sessions": sessions}, sort_keys=False))
    return path


def main() -> int:
    base = yaml.safe_load((ROOT / "configs" / "study.yaml").read_text())
    RUNS.mkdir(parents=True, exist_ok=True)
    sessions = []
    for subject in GROWTH:
        for i, day in enumerate(DAYS):
            for filt in FILTERS:
                name = f"{subject}-d{day}-{filt}"
                rec = run_session(session_config(base, subject, i, filt, RUNS / name), name)
                sessions.append({"artefact": str(rec.relative_to(RUNS)), "subject": subject, "day": day, "filter": filt})
                print(f"session {name}: {rec}", flush=True)
    main_study = study_file(RUNS / "growth.yaml", sessions, "simulated study: a growing source, 2 subjects x 3 days x 2 filters")
    r = subprocess.run([FLUXMAP, "study", str(main_study)], capture_output=True, text=True)
    print(r.stdout[-4000:], r.stderr[-2000:])
    if r.returncode != 0:
        return r.returncode
    ok = check_growth(RUNS / "out" / "growth" / "study.csv")

    # another camera calibration (a refitted focal length): flagged, naming the difference
    recal = run_session(session_config(base, "m1", 1, "F520", RUNS / "m1-d7-F520-recal", focal_mm=24.4), "recal")
    mixed = study_file(RUNS / "mixed.yaml", sessions[:6] + [
        {"artefact": str(recal.relative_to(RUNS)), "subject": "m1", "day": 7, "filter": "F520", "label": "m1 day 7 F520 (recalibrated)"}],
        "a study mixing two camera calibrations")
    r = subprocess.run([FLUXMAP, "study", str(mixed), "-q"], capture_output=True, text=True)
    flagged = r.returncode == 0 and "focal_length_mm" in r.stderr
    print(f"mixed calibrations: exit {r.returncode}; flagged: {flagged}\n  {r.stderr.strip()[:600]}")
    ok &= flagged

    # an artefact changed after the fact: refused, naming it
    bad = RUNS / "tampered" / "reconstruction.h5"
    bad.parent.mkdir(exist_ok=True)
    shutil.copy(RUNS / "m1-d10-F520" / "reconstruction.h5", bad)
    with h5py.File(bad, "r+") as f:
        f["rois/total_photons_per_s"][0, -1] *= 1.25  # someone "corrects" day 10
    tampered = study_file(RUNS / "tampered.yaml", sessions[:4] + [
        {"artefact": str(bad.relative_to(RUNS)), "subject": "m1", "day": 10, "filter": "F520"}], "a tampered study")
    r = subprocess.run([FLUXMAP, "study", str(tampered), "-q"], capture_output=True, text=True)
    refused = r.returncode == 2 and str(bad) in " ".join(r.stderr.split()).replace("\n", "")
    print(f"tampered artefact: exit {r.returncode}; refused naming it: {refused}\n  {' '.join(r.stderr.split())[:400]}")
    ok &= refused

    page = RUNS / "out" / "growth" / "index.html"
    from fluxcli.report import browser_check as B

    if B.find_chromium() is None:
        print("study page: no Chromium here, not opened (Debian: apt-get install chromium)")
    else:
        shot = page.with_name("screenshot.png")
        console = B.screenshot(page, shot, height=1600)
        errors = [c for c in console if not any(b in c for b in B.BENIGN)]
        from matplotlib.image import imread

        drawn = B.coloured_fraction((imread(shot)[:, :, :3] * 255).astype(np.uint8))
        print(f"study page in headless Chromium: {len(errors)} console message(s) {errors[:3]}; "
              f"{drawn:.1%} coloured pixels in the screenshot {shot}")
        ok &= not errors and drawn > 0.001
    print(f"study: {'all checks hold' if ok else 'A CHECK FAILED'}; table {RUNS / 'out' / 'growth' / 'study.csv'}, "
          f"page {page}")
    return 0 if ok else 1


def check_growth(csv_path: Path) -> bool:
    """Per subject and filter: fluxmap's joint ROI total over days against the true growth,
    and the direct-view image sum per pose against each other."""
    rows = list(csv.DictReader(csv_path.open()))
    ok = True
    print("\nROI 'tumour', joint over the poses: total / day-3 total, fluxmap against the truth")
    print(f"{'subject':8} {'filter':7} {'day':>4} {'total ph/s':>12} {'± 1 sd':>9} {'truth ph/s':>12} {'growth':>7} "
          f"{'true':>7} {'diff':>7}   direct-view image sum per pose (ph/s), pose 2 / pose 1")
    for subject in GROWTH:
        for filt in FILTERS:
            j = sorted((r for r in rows if r["subject"] == subject and r["filter"] == filt and r["roi"] == "tumour"
                        and r["pose"] == "joint"), key=lambda r: float(r["day"]))
            t0, g0 = float(j[0]["total_photons_per_s"]), float(j[0]["true_total_photons_per_s"])
            for r in j:
                grow, true = float(r["total_photons_per_s"]) / t0, float(r["true_total_photons_per_s"]) / g0
                per = [float(x["direct_image_photons_per_s"]) for x in rows if x["session"] == r["session"]
                       and x["roi"] == "tumour" and x["pose"] != "joint"]
                diff = grow / true - 1
                ok &= abs(diff) <= GROWTH_TOL
                print(f"{subject:8} {filt:7} {r['day']:>4} {float(r['total_photons_per_s']):12.4g} "
                      f"{float(r['sigma_photons_per_s']):9.2g} {float(r['true_total_photons_per_s']):12.4g} {grow:7.3f} "
                      f"{true:7.3f} {diff:+7.2%}   {', '.join(f'{p:.3g}' for p in per)}  ({per[1] / per[0]:.2f})")
    swing = [float(x["direct_image_photons_per_s"]) for x in rows if x["pose"] == "2" and x["roi"] == "tumour"]
    base_ = [float(x["direct_image_photons_per_s"]) for x in rows if x["pose"] == "1" and x["roi"] == "tumour"]
    ratio = np.array(swing) / np.array(base_)
    print(f"direct-view image sum, pose 2 over pose 1, across sessions: {ratio.min():.2f} to {ratio.max():.2f} "
          f"(fluxmap's per-pose ROI totals are in study.csv too); growth within {GROWTH_TOL:.0%}: {ok}")
    ok &= bool(np.all(np.abs(ratio - 1) > 0.1))
    return ok


if __name__ == "__main__":
    sys.exit(main())
