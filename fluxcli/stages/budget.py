"""reconstruct's error budget: every total's σ from photon noise, regularisation and calibration.

reconstruct calls :func:`error_budget` once after its solves and :func:`write` once inside
reconstruction.h5 (``/budget``).  The science is :mod:`fluxcli.quantify.budget`.

Photon noise is measured on every run (from each solve's covariance, while it is alive:
:class:`TotalMeter`).  Regularisation and calibration need more solves and, for the
calibration, one T build per calibrated parameter (and pose): they run only when the
config states the camera's 1 σ (``system.camera.uncertainty``, what calibrate writes) or
a mirror's (``normal_sigma_deg``, ``offset_sigma_mm``), and ``reconstruct.calibration_budget``
is not false.  The count of T builds is printed before they start.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from .. import config as C
from ..errors import UserError
from ..imaging.fit_shift import shifts, with_shift_warnings  # noqa: F401 (reconstruct's)
from ..quantify import budget as Q
from ..surface.geometry import rotation_matrix


# ------------------------------------------------------------------ photon noise, on every run
SLOW_SOLVE_S = 5.0  # a solve that took longer says so when it ends (what a long reconstruct is doing)


class TotalMeter:
    """σ of each solve's total under the images' noise, measured while its covariance lives;
    with ``ctx``, a line after each solve once the solves have taken more than SLOW_SOLVE_S
    (which solve of how many, how long, the time left at that pace)."""

    def __init__(self, ctx=None, n_solves: int = 0):
        self.sigma: dict[str, float] = {}
        self.ctx, self.n = ctx, n_solves
        self.t0 = self.last = time.perf_counter()

    def __bool__(self) -> bool:
        return True

    def measure(self, label: str, height_mm, rotation_deg, res) -> None:
        self.sigma[label] = Q.total_sigma_noise(res)
        now = time.perf_counter()
        done = len(self.sigma)
        if self.ctx is not None and now - self.t0 > SLOW_SOLVE_S:
            left = (now - self.t0) / done * (self.n - done) if self.n > done else 0.0
            what = "all poses jointly" if label == "joint" else f"pose {label}"
            self.ctx.say(f"reconstruct: solved {what} ({done} of {self.n}) in {now - self.last:.0f} s"
                         + (f"; about {left:.0f} s to go" if left > 0 else ""))
        self.last = now


class Both:
    """Two meters where reconstruct takes one (its ROI meter, and the totals' meter)."""

    def __init__(self, *meters):
        self.meters = [m for m in meters if m]

    def __bool__(self) -> bool:
        return bool(self.meters)

    def measure(self, *args) -> None:
        for m in self.meters:
            m.measure(*args)


# ------------------------------------------------------------------ the calibration's parameters
def _rotate(v, axis, angle_deg: float) -> tuple[float, float, float]:
    """``v`` rotated by ``angle_deg`` about the unit ``axis`` (Rodrigues)."""
    return tuple(float(x) for x in rotation_matrix(axis, angle_deg) @ np.asarray(v, float))


def _with_camera(system: C.System, **parts) -> C.System:
    cam = system.camera
    return system.model_copy(update={"camera": cam.model_copy(update=parts)})


def _lens(cam: C.Camera, **update) -> C.Lens:
    """The lens with ``update``; the aperture held as a diameter (so that moving f keeps it)."""
    lens = cam.lens
    base = {"aperture_diameter_mm": 2 * lens.aperture_radius_mm, "f_number": None}
    return lens.model_copy(update=base | update)


def parameters(system: C.System) -> list[tuple[str, float, str, C.System]]:
    """Every calibrated parameter with a stated 1 σ, as (name, σ, unit, the system with it moved
    by +1 σ).  The optical axis and each mirror normal are tilted about two perpendicular axes."""
    cam = system.camera
    unc = cam.uncertainty
    out = []
    if unc is not None:
        pose, lens = cam.pose, cam.lens
        if unc.lens_center_mm is not None:
            for i, ax in enumerate("xyz"):
                s = unc.lens_center_mm[i]
                if s > 0:
                    c = list(pose.lens_center_mm)
                    c[i] += s
                    out.append((f"lens_center_mm.{ax}", s, "mm",
                                _with_camera(system, pose=pose.model_copy(update={"lens_center_mm": tuple(c)}))))
        if unc.look_deg:
            look = np.asarray(pose.look, float) / np.linalg.norm(pose.look)
            up = np.asarray(pose.up, float)
            right = np.cross(look, up)
            up_perp = np.cross(right, look)
            for name, axis in (("look_deg.pan", up_perp), ("look_deg.tilt", right)):
                out.append((name, unc.look_deg, "deg", _with_camera(system, pose=pose.model_copy(update={
                    "look": _rotate(look, axis, unc.look_deg), "up": _rotate(up, axis, unc.look_deg)}))))
        for key, unit in (("focal_length_mm", "mm"), ("focus_distance_mm", "mm"), ("aperture_diameter_mm", "mm")):
            s = getattr(unc, key)
            if s:
                now = 2 * lens.aperture_radius_mm if key == "aperture_diameter_mm" else getattr(lens, key)
                out.append((key, s, unit, _with_camera(system, lens=_lens(cam, **{key: now + s}))))
    for k, m in enumerate(system.mirrors):
        name = m.name or f"mirror{k}"
        n = np.asarray(m.normal, float) / np.linalg.norm(m.normal)
        if m.offset_sigma_mm:
            moved = m.model_copy(update={"center_mm": tuple(float(x) for x in np.asarray(m.center_mm) + m.offset_sigma_mm * n)})
            out.append((f"mirror {name} offset_mm", m.offset_sigma_mm, "mm", _with_mirror(system, k, moved)))
        if m.normal_sigma_deg:
            u = np.asarray(m.axis, float) / np.linalg.norm(m.axis)
            v = np.cross(n, u)
            for label, ax in (("about its axis", u), ("across its axis", v)):
                moved = m.model_copy(update={"normal": _rotate(n, ax, m.normal_sigma_deg),
                                             "axis": _rotate(u, ax, m.normal_sigma_deg)})
                out.append((f"mirror {name} normal_deg {label}", m.normal_sigma_deg, "deg", _with_mirror(system, k, moved)))
    for name, s, unit, moved in out:
        _check_movable(name, s, unit, moved)
    return out


def _check_movable(name: str, s: float, unit: str, moved: C.System) -> None:
    """A UserError naming the uncertainty when moving its parameter by +1 sd leaves no camera."""
    from ..scene import camera_from_config

    try:
        camera_from_config(moved.camera)
    except ValueError as e:
        where = f"system.camera.uncertainty.{name.split('.')[0]}" if not name.startswith("mirror ") else name
        raise UserError(f"{where}: the error budget moves {name} by its 1 sd of {s:g} {unit}, and the camera it "
                        f"gives is impossible ({e}). A 1 sd is the spread of a measurement and must be small against "
                        "the value it qualifies: check the number (and its unit), or leave it out to skip that "
                        "parameter's share of the budget.") from None


def _with_mirror(system: C.System, k: int, mirror: C.Mirror) -> C.System:
    mirrors = list(system.mirrors)
    mirrors[k] = mirror
    return system.model_copy(update={"mirrors": tuple(mirrors)})


def gain_relative(system: C.System) -> float | None:
    unc = system.camera.uncertainty
    return unc.gain_relative if unc is not None else None


def wanted(system: C.System, calibration_budget: bool) -> bool:
    """Whether reconstruct computes the regularisation and calibration parts."""
    s = system
    return bool(calibration_budget and (s.camera.uncertainty is not None or any(
        m.normal_sigma_deg or m.offset_sigma_mm for m in s.mirrors)))


# ------------------------------------------------------------------ the budget
@dataclass
class Budget:
    totals: list  # [Q.TotalBudget] per pose, then joint
    shifts: list  # [Q.Shift] per pose
    parameters: list = field(default_factory=list)  # [(name, sigma, unit)]
    gain_relative: float | None = None
    t_builds: int = 0
    exposure_s: float | None = None
    roi_names: list = field(default_factory=list)
    roi_sigma_regularisation: np.ndarray | None = None  # (n_roi, n_totals) photons
    roi_sigma_calibration: np.ndarray | None = None  # (n_roi, n_totals) photons

    def lines(self) -> list[str]:
        """Console lines: every total ± σ with the parts."""
        t = self.exposure_s
        out = []
        for b in self.totals:  # photons, as the total lines above; the rate beside when the exposure is known
            parts = [f"photon noise {b.sigma_noise:.2g}"]
            if np.isfinite(b.sigma_regularisation):
                parts.append(f"regularisation {b.sigma_regularisation:.2g}")
            if np.isfinite(b.sigma_calibration):
                parts.append(f"calibration {b.sigma_calibration:.2g}")
            rate = f" = {b.total / t:.4g} ± {b.sigma / t:.2g} photons/s" if t else ""
            out.append(f"error budget, {b.label}: {b.total:.4g} ± {b.sigma:.2g} photons over observed elements{rate} "
                       "(1 sd: " + ", ".join(parts) + ")")
        if not self.parameters and self.gain_relative is None:
            out.append("error budget: photon noise only; the calibration's error and the regularisation's are not "
                       "included (system.camera.uncertainty not given: calibrate writes it)")
        if self.parameters:
            big = max(self.totals, key=lambda b: b.sigma_calibration if np.isfinite(b.sigma_calibration) else -1)
            top = sorted(big.deltas.items(), key=lambda kv: -abs(kv[1]))[:3]
            out.append(f"calibration: {len(self.parameters)} parameter(s) moved by +1 sd ({self.t_builds} T builds)"
                       + (f", gain {self.gain_relative:.1%}" if self.gain_relative else "")
                       + f"; largest in {big.label}: " + ", ".join(
                           f"{k} {v / big.total:+.1%}" if big.total else f"{k} {v:.3g}" for k, v in top))
        return out


def noise_only(meter: TotalMeter, per_pose, joint, labels: list[str], exposure_s) -> Budget:
    """The budget of a run without the calibration's σ: photon noise alone."""
    totals = [Q.TotalBudget(f"pose {lab}", float(np.nansum(r.power)), sigma_noise=meter.sigma.get(str(k + 1), np.nan))
              for k, ((r, _), lab) in enumerate(zip(per_pose, labels))]
    if joint is not None:
        totals.append(Q.TotalBudget("all poses jointly", float(np.nansum(joint.power)),
                                    sigma_noise=meter.sigma.get("joint", np.nan)))
    return Budget(totals, [], exposure_s=exposure_s)


def error_budget(system: C.System, calibration_budget: bool, build_T, ctx, surface, m: C.MethodSettings, gm, inp,
                 noise, per_pose, joint, todo, scale: float, meter: TotalMeter, exposure_s, rois=None) -> Budget:
    """The budget of every total: photon noise always; with the calibration's σ given, the
    regularisation (λ halved and doubled) and the calibration (one T per parameter at +1 σ,
    each pose solved again at its own λ).  With ``rois`` (the run's RoiMeter, which measured
    each solve) every region's total gets its regularisation and calibration σ too, over the
    region's members as measured on the solve as used.  ``system``: the rig whose calibrated
    parameters move; ``build_T``: the run plan's T builder."""
    from ..inverse.solve import run_method
    from ._reconstruct_grid import make_grid

    labels = [pt.pose.label for _, pt in todo]
    b = noise_only(meter, per_pose, joint, labels, exposure_s)
    b.shifts = shifts(per_pose, inp.images, inp.valid, noise)
    if not wanted(system, calibration_budget):
        return b
    params = parameters(system)
    b.parameters = [(n, s, u) for n, s, u, _ in params]
    b.gain_relative = gain_relative(system)
    b.t_builds = len(params) * len(todo)
    ctx.say(f"error budget: {len(params)} calibrated parameter(s) moved by +1 sd: {b.t_builds} T builds "
            f"({len(params)} x {len(todo)} pose(s); the T cache keeps them, a rerun only solves), then each pose "
            "and the joint set solved again at its lambda, and at lambda halved and doubled")
    P = len(todo)
    results = [r for r, _ in per_pose] + ([joint] if joint is not None else [])

    def solve(Ts, parts_k, k, lam):  # k: pose, or None for joint
        mk = m.model_copy(update={"lam": float(lam)}) if lam is not None and m.method != "mlem" else m
        if k is None:
            T, a, valid = sp.vstack(Ts).tocsr(), inp.images, inp.valid
        else:
            T, a, valid = Ts[k], inp.images[k], inp.valid[k]
        res, _ = run_method(T, a, valid, mk, noise, gm.adjacency, parts_k, gm.n_elements, gm.areas)
        return np.asarray(res.power, float) / scale

    def each(Ts, parts_of, lam_factor=1.0):
        out = []
        for i, r in enumerate(results):
            k = i if i < P else None
            lam = None if r.lam is None else r.lam * lam_factor
            out.append(solve(Ts, parts_of(k), k, lam))
        return out

    quiet = replace(ctx, quiet=True)
    with ctx.progress_steps("error budget", 3 + len(params)) as step:
        step("lambda as used")
        base = each(gm.Ts, gm.parts, 1.0)
        step("lambda halved", advance=True)
        half = each(gm.Ts, gm.parts, 0.5)
        step("lambda doubled", advance=True)
        double = each(gm.Ts, gm.parts, 2.0)
        moved_all = []
        for name, _, _, moved in params:
            step(f"T with {name} + 1 sd", advance=True)
            g = make_grid(build_T, quiet, surface, m.unknowns, moved)
            moved_all.append(each(g.Ts, g.parts, 1.0))
        step("done", advance=True)
    # the totals (each over its own observed elements), then each region's (over its members)
    members = [np.ones((1, gm.n_elements), bool) for _ in results]
    if rois and len(getattr(rois, "members", [])) == len(results):
        members = [np.vstack([np.ones((1, gm.n_elements), bool), np.asarray(M, bool)]) for M in rois.members]
        b.roi_names = [r.name for r in rois.regions]

    def sums(power, i):  # (1 + n_roi,) photons: the total and each region's, unobserved elements left out
        return np.where(members[i], np.nan_to_num(power, nan=0.0)[None, :], 0.0).sum(axis=1)

    n_roi = len(b.roi_names)
    roi_reg = np.full((n_roi, len(results)), np.nan)
    roi_cal = np.full((n_roi, len(results)), np.nan)
    for i, tb in enumerate(b.totals):
        t0, th, td = sums(base[i], i), sums(half[i], i), sums(double[i], i)
        d = np.array([sums(mv[i], i) - t0 for mv in moved_all]).reshape(len(params), -1)
        reg = np.maximum(np.abs(th - t0), np.abs(td - t0))
        g_rel = b.gain_relative or 0.0
        cal = np.sqrt(np.sum(d ** 2, axis=0) + (np.r_[tb.total, t0[1:]] * g_rel) ** 2)
        tb.sigma_regularisation = float(reg[0])
        tb.deltas = {name: float(d[j, 0]) for j, (name, *_) in enumerate(params)}
        tb.sigma_gain = tb.total * g_rel
        tb.sigma_calibration = Q.calibration_sigma(tb.total, list(tb.deltas.values()), b.gain_relative)
        roi_reg[:, i], roi_cal[:, i] = reg[1:], cal[1:]
    if n_roi:
        b.roi_sigma_regularisation, b.roi_sigma_calibration = roi_reg, roi_cal
    return b
