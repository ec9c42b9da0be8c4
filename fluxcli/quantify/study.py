"""Sessions x regions of interest: the tidy table of a study, and whether its sessions
were made with the same set-up.

A *session* is one reconstruction (its ``/rois`` numbers) of one subject on one day, with
one filter.  :func:`tidy_rows` turns sessions into rows (session x ROI x filter x map, the
map being each pose and ``joint``); :func:`setup_of` takes from a reconstruction's recorded
config what makes its numbers comparable with another's (camera and calibration, emission
model, units and exposure) and :func:`setup_differences` names what differs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..artefacts.store import geometry_differences


@dataclass(frozen=True)
class Session:
    """One reconstruction of a study, read from its artefact."""

    label: str  # as the study file names it
    subject: str
    day: float | None
    date: str | None
    filter: str
    artefact: str  # path as given
    rois: dict  # fluxcli.artefacts.reconstruction.read_rois(...)
    direct_image_photons: np.ndarray  # (n_poses,) photons summed over the direct view's pixels, per exposure
    heights_mm: np.ndarray
    rotations_deg: np.ndarray
    setup: dict
    truth_rois: dict | None = None  # roi name -> true total (photons/s) when the images were simulated


def setup_of(config: dict, input_files: dict) -> dict:
    """What makes two sessions' numbers comparable, from a reconstruction's resolved config
    (``config_json``) and recorded input files."""
    system = config.get("system") or {}
    cam = dict(system.get("camera") or {})
    subject = config.get("subject") or {}
    rc = config.get("reconstruct") or {}
    images = rc.get("images") or {}
    sim = config.get("simulate") or {}
    cal = {k: v.get("sha256") for k, v in (input_files or {}).items() if "calibration" in k}
    return {
        "camera": {k: cam.get(k) for k in ("pixels", "pixel_pitch_mm", "lens", "pose", "apertures", "sensor", "binning")
                   if k in cam},
        "mirrors": system.get("mirrors"),
        "calibration": cal or None,
        "emission": subject.get("emission", {"model": "lambertian"}),
        "units": {"images": images.get("units", "photons"),
                  "exposure_s": images.get("exposure_s", (sim.get("noise") or {}).get("exposure_s"))},
    }


def setup_differences(reference: dict, other: dict, name: str) -> list[str]:
    """``key: VALUE in NAME, VALUE in the reference`` for every set-up key that differs."""
    return [d.replace(" now", " in the first session") for d in geometry_differences(other, reference, name)]


def study_rows(sessions: list[Session], flags: dict[str, str]) -> tuple[list[str], list[list]]:
    """The tidy table: one row per session x ROI x map (each pose, then ``joint``), the
    session's filter and its set-up flag on every row.  ``direct_image_photons_per_s`` is
    the older number: photons summed over the pixels the direct view reaches, per pose
    (the same for every ROI: the image region labs draw, not the surface region)."""
    from ..artefacts.reconstruction import ROI_NUMBER_KEYS as NUMBER_KEYS

    header = ["subject", "day", "date", "filter", "session", "roi", "pose", "height_mm", "rotation_deg",
              *NUMBER_KEYS, "true_total_photons_per_s", "direct_image_photons_per_s", "status", "setup_flag"]
    rows = []
    for s in sessions:
        r = s.rois
        t = r["exposure_s"] if r["exposure_s"] is not None else 1.0
        for i, name in enumerate(r["names"]):
            for m, label in enumerate(r["maps"]):
                pose = label != "joint"
                k = int(label) - 1 if pose else None
                rows.append([s.subject, "" if s.day is None else f"{s.day:g}", s.date or "", s.filter, s.label, name,
                             label, f"{s.heights_mm[k]:g}" if pose else "", f"{s.rotations_deg[k]:g}" if pose else "",
                             *(f"{r['numbers'][key][i, m]:.8g}" for key in NUMBER_KEYS),
                             f"{s.truth_rois[name]:.8g}" if s.truth_rois and name in s.truth_rois else "",
                             f"{s.direct_image_photons[k] / t:.8g}" if pose else "",
                             r["status"][i, m], flags.get(s.label, "")])
    return header, rows
