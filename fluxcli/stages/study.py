"""``fluxmap study STUDY.yaml``: regions of interest over sessions, subjects and filters.

Examples
--------
$ fluxmap study studies/tumour.yaml

STUDY.yaml lists sessions, each a reconstruction artefact with the subject and a day (or a
date), optionally its filter, and which regions of interest to report (default: every
region the sessions share)::

    title: tumour growth
    output: out/tumour          # folder, relative to this file (default study/<name>)
    rois: [tumour]
    sessions:
      - {artefact: ../runs/m1-d3/reconstruction.h5, subject: m1, day: 3, filter: GFP}
      - {artefact: ../runs/m1-d7/reconstruction.h5, subject: m1, day: 7, filter: GFP}

Writes ``study.csv`` (one row per session x region x pose, the joint reconstruction as pose
``joint``, with σ) and ``index.html`` (totals over time per subject with error bars, next to
the direct-view image sum of each pose).  Sessions whose set-up (camera, calibration,
emission model, units) differs from the first one's are flagged, naming what differs.  An
artefact whose results changed after it was written (its recorded digest), or whose input
files changed since, is refused (exit 2), naming the file.  An artefact of several filters (one
reconstruct through each) gives a part per filter; a session that names a filter takes that
one, and one the artefact does not hold is refused.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from .. import artefacts as A
from .. import config as C
from ..artefacts.reconstruction import read_for_study
from ..errors import UserError
from ..quantify.study import Session, setup_differences, setup_of, study_rows
from .context import RunContext


class StudySession(C.Model):
    """One reconstruction of the study."""

    artefact: Path = Field(description="A reconstruction.h5, relative to the study file.")
    subject: str = Field(min_length=1, description="The animal or phantom (its id).")
    day: float | None = Field(None, description="Day of the session (e.g. days after implantation).")
    date: str | None = Field(None, description="Date of the session (ISO, e.g. 2026-11-20, or 2026-11-20 10:30 for "
                             "time points within a day), when no day is given.")
    filter: str = Field("-", description="The emission filter of the images (free text).")
    label: str | None = Field(None, description="Name of the session in tables (default subject/day/filter).")

    @model_validator(mode="after")
    def _when(self) -> "StudySession":
        if self.day is None and self.date is None:
            raise ValueError("a session needs a day or a date")
        return self

    @field_validator("date", mode="before")
    @classmethod
    def _iso(cls, v):
        """An ISO date, or date and time (a kinetic series within a day), written as ISO so that
        the table and the plot's axis sort by time; YAML reads an unquoted 2026-11-20 (and
        2026-11-20 10:30:00) as a date (a datetime) already."""
        if v is None or isinstance(v, datetime.date):
            return v if v is None else v.isoformat(sep=" ") if isinstance(v, datetime.datetime) else v.isoformat()
        if isinstance(v, str):
            for kind in (datetime.date, datetime.datetime):
                try:
                    t = kind.fromisoformat(v.strip())
                    return t.isoformat(sep=" ") if kind is datetime.datetime else t.isoformat()
                except ValueError:
                    pass
        raise ValueError(f"{v!r} is not an ISO date (YYYY-MM-DD, e.g. 2026-11-20) or date and time "
                         "(2026-11-20 10:30)")

    @property
    def name(self) -> str:
        return self.label or f"{self.subject} {'day ' + format(self.day, 'g') if self.day is not None else self.date} {self.filter}"


class StudyFile(C.Model):
    title: str | None = Field(None, description="Page title (default: the study file's name).")
    output: Path | None = Field(None, description="Output folder, relative to the study file (default study/<name>).")
    rois: tuple[str, ...] | None = Field(None, min_length=1, description="Regions to report (default: all the sessions share).")
    sessions: tuple[StudySession, ...] = Field(min_length=1, description="The sessions.")

    @model_validator(mode="after")
    def _one_time_axis(self) -> "StudyFile":
        """A subject's sessions lie on one time axis: all by day, or all by date."""
        by_day = {}
        for k, s in enumerate(self.sessions):
            by_day.setdefault(s.subject, {}).setdefault(s.day is not None, k)
        for subject, kinds in by_day.items():
            if len(kinds) == 2:
                d, t = kinds[True], kinds[False]
                raise ValueError(f"subject {subject!r}: sessions[{d}] ({self.sessions[d].name}) gives a day and "
                                 f"sessions[{t}] ({self.sessions[t].name}) only a date; give all of a subject's "
                                 "sessions a day, or all of them a date, so that they share one time axis")
        return self


def load_study(path: Path) -> StudyFile:
    path = Path(path)
    if path.is_dir():
        raise UserError(f"study file {path} is a folder; give the study's YAML file itself.")
    if not path.is_file():
        raise UserError(f"study file {path} does not exist.")
    try:
        raw = yaml.load(path.read_text(), Loader=C._UniqueKeyLoader)
    except yaml.YAMLError as e:
        raise UserError(f"study file {path} is not valid YAML: {C._yaml_problem(e)}.") from None
    try:
        return StudyFile.model_validate(raw if raw is not None else {})
    except ValidationError as e:
        raise UserError(C._format_validation_error(e, path, raw, what="study file")) from None


def read_session(s: StudySession, k: int, base: Path) -> list[Session]:
    """The session's numbers (one per filter of the artefact), refusing an artefact changed
    after the fact."""
    path = s.artefact if s.artefact.is_absolute() else (base / s.artefact).resolve()
    where = f"sessions[{k}] ({s.name})"
    try:
        view = read_for_study(path, s.filter)
    except UserError as e:
        raise UserError(f"{where}: {e}") from None
    if view.unchanged is None:
        raise UserError(f"{where}: {path} records no digest of its results (made by an older fluxmap), so it "
                        "cannot be checked; reconstruct it again.")
    if not view.unchanged:
        raise UserError(f"{where}: {path} was changed after it was written: its results no longer match the "
                        "digest recorded when reconstruct made it. Refusing it; reconstruct it again from its images.")
    prov = view.provenance
    for name, rec in prov.input_files.items():
        p = path.parent / rec.get("path", "")
        if p.is_file() and A.file_sha256(p) != rec.get("sha256"):
            raise UserError(f"{where}: {p} ({name}) changed after {path} was made from it; the reconstruction no "
                            "longer matches its input. Refusing it; reconstruct it again.")
    if not view.has_rois:
        raise UserError(f"{where}: {path} holds no regions of interest; give rois: in its config and reconstruct "
                        "it again.")
    parts = view.parts
    names = [filt for filt, *_ in parts]
    if s.filter != "-" and names != [s.filter]:  # an artefact of several filters: the one the study names
        if s.filter not in names:
            raise UserError(f"{where}: filter {s.filter!r} is not among the filters {path} was reconstructed through "
                            f"({', '.join(names)}); name one of them, or leave filter out to take them all.")
        parts = [x for x in parts if x[0] == s.filter]
    out = []
    for filt, rois, power, direct in parts:
        truth = None
        if power is not None:
            t = rois["exposure_s"] if rois["exposure_s"] is not None else 1.0
            truth = {n: float(power[rois["members"][i, -1]].sum()) / t for i, n in enumerate(rois["names"])}
        label = s.name if len(parts) == 1 else f"{s.label or s.subject + ' ' + ('day ' + format(s.day, 'g') if s.day is not None else s.date)} {filt}"
        out.append(Session(label=label, subject=s.subject, day=s.day, date=s.date, filter=filt, artefact=str(path),
                           rois=rois, direct_image_photons=direct, heights_mm=view.heights_mm,
                           rotations_deg=view.rotations_deg,
                           setup=setup_of(prov.config, prov.input_files), truth_rois=truth))
    return out


def _keep(session: Session, names: tuple[str, ...], where: str) -> Session:
    r = session.rois
    missing = [n for n in names if n not in r["names"]]
    if missing:
        raise UserError(f"{where}: {session.artefact} has no region {', '.join(missing)} (it has "
                        f"{', '.join(r['names'])}).")
    idx = [r["names"].index(n) for n in names]
    sub = dict(r, names=list(names), definitions=[r["definitions"][i] for i in idx] if r["definitions"] else [],
               numbers={k: v[idx] for k, v in r["numbers"].items()}, status=r["status"][idx], members=r["members"][idx])
    return Session(**{**session.__dict__, "rois": sub})


def _one_measurement_once(sessions, base: Path) -> None:
    """One artefact (and filter) is one measurement: listed in two sessions it would be counted
    twice, or read as two time points (a line copied and its day changed, its artefact not)."""
    seen = {}
    for k, s in enumerate(sessions):
        path = s.artefact if s.artefact.is_absolute() else (base / s.artefact).resolve()
        j = seen.setdefault((path, s.filter), k)
        if j != k:
            raise UserError(f"sessions[{j}] ({sessions[j].name}) and sessions[{k}] ({s.name}) both read {path}"
                            + (f" through filter {s.filter}" if s.filter != "-" else "") + ": one measurement "
                            "cannot be two sessions; give each session its own artefact.")


def run(study_path: Path, ctx: RunContext) -> Path:
    study_path = Path(study_path).resolve()
    st = load_study(study_path)
    base = study_path.parent
    _one_measurement_once(st.sessions, base)
    sessions = [x for k, s in enumerate(st.sessions) for x in read_session(s, k, base)]
    names = st.rois or tuple(n for n in sessions[0].rois["names"] if all(n in s.rois["names"] for s in sessions))
    if not names:
        raise UserError(f"{study_path}: the sessions share no region of interest; name them in rois:.")
    sessions = [_keep(s, names, f"sessions[{k}] ({s.label})") for k, s in enumerate(sessions)]
    ref = sessions[0]
    flags = {}
    for s in sessions[1:]:
        diffs = setup_differences(ref.setup, s.setup, Path(s.artefact).name)
        if diffs:
            flags[s.label] = "set-up differs from the first session (" + ref.label + "): " + "; ".join(diffs[:6]) + (
                f" (and {len(diffs) - 6} more)" if len(diffs) > 6 else "")
    notes = [f"session {s.label}: totals per exposure (no exposure time recorded)" for s in sessions
             if s.rois["exposure_s"] is None]
    header, rows = study_rows(sessions, flags)
    out = (base / st.output) if st.output is not None else base / "study" / study_path.stem
    out.mkdir(parents=True, exist_ok=True)
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    A.write_text(out / "study.csv", buf.getvalue())
    from ..report.study_page import study_page

    A.write_text(out / "index.html", study_page(st.title or study_path.stem, header, rows, flags, notes))
    A.write_text(out / "flags.json", json.dumps(flags, indent=1))
    for label, text in flags.items():
        ctx.warn(f"{label}: {text}")
    joint = [r for r in rows if r[header.index("pose")] == "joint"]
    ctx.table(["subject", "day/date", "filter", "roi", "total (photons/s) ± 1 sd", "status"],
              [[r[0], r[1] or r[2], r[3], r[5], f"{float(r[header.index('total_photons_per_s')]):.4g} ± "
                f"{float(r[header.index('sigma_photons_per_s')]):.2g}", r[header.index("status")]] for r in joint])
    ctx.say(f"study: {len(sessions)} session(s), {len(names)} region(s): {out / 'study.csv'}")
    return out / "index.html"
