"""Is the light sharper than the surface's unknowns can follow?

Reconstruct models the exitance as linear within each face (vertex unknowns) or constant within
each element.  A source just under the skin (2 mm under tissue at n 1.56, as in the Monte Carlo
battery) makes a spot whose half-maximum is narrower than one 4-mm element: no exitance the
unknowns can take puts that much light into so few pixels, so the fit spreads the peak's light
over the elements around it.  The image then holds far more light at its peak than the fit
(+69 %, χ² 25.8 per pixel on the battery's `box-n1.56-shallow2` head-on), and every other
check misreads the misfit: "the images and the set-up disagree in kind", "the image shifted by
0.6 pixels", "structured by viewing angle".  None of those is the cause, and a user who follows
them recalibrates a camera that is right.  The totals are little affected (0.985-1.006 there);
the map near the peak is (18 % error; 3.0 % with each face split in four).

The test (:func:`sharp_peak`): the core of the brightest spot (the pixels at or above half the
maximum of the 3 x 3-smoothed image) holds significantly more light than the fit there, the fit
does not explain the image (χ² per pixel above :data:`CHI2_MAX`), the light is missing all over
the core (where the fit is brighter than the image it makes up at most a third of what it lacks
elsewhere there: a shifted spot leaves a residual of both signs, 0.63 for a 0.5-pixel shift of a
spot 1.2 pixels wide, 0.005-0.11 on the battery's shallow source), and the core covers fewer
pixels than the unit the unknowns vary over: the footprint of the element that lights the core
most (its T column's participation ratio (Σ T)² / Σ T², blur included) over the unknowns per
element (vertices of the faces, about 4x more per level of ``subject.refine_faces``).

A camera a calibration error away leaves a residual of both signs along the image's gradients
(the shift test), not light missing at the peak; a wrong emission profile misjudges elements by
viewing angle, a few per cent (the battery's other cases: at most 4.1 % at the core, χ² below 2);
neither fires this.  A lens model that blurs more than the real lens does leave light missing at
the peak, and so does a small bright reflection the subject's light does not explain; the warning
names both, after the faces.  With the warning, the χ² and viewing-angle warnings of
the pose (:data:`EXPLAINED`) and its shift warning are not given: they would send the user to the
camera or the emission model for a misfit that is neither's.

A spot a few unknowns wide (:attr:`SharpPeak.near`, :func:`near_note`): the core wider than one
unknown but narrower than :data:`NEAR_UNITS` of them, with most of the pose's χ² excess in and
around it.  Pixels about as coarse as the unknowns cannot tell that misfit from a camera model
that does not match the images, so the χ² warning stays and a note names both readings and the
test that tells them apart (the next ``subject.refine_faces``).  `make study`'s day-3 sessions
(a 2.5-mm source on 3.3 x 4.2-mm elements through 2.3-mm pixels) were told only that the images
and the set-up disagree in kind (χ² 31); with the faces split once χ² is 3.8.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

CHI2_MAX = 2.0  # the fit must be poor (filtered.CHI2_RANGE's top): a peak the data cannot tell apart is not one to warn of
MIN_EXCESS = 0.05  # the core's light beyond the fit, over the fit there
MIN_Z = 5.0  # ... in standard errors of the core's photons
MAX_NEGATIVE = 1.0 / 3.0  # the fit's light above the image's in the core, at most this share of the image's above the fit
HALF = 0.5  # the core: at or above half the smoothed image's maximum
NEAR_UNITS = 4.0  # a core narrower than this many unknowns' footprints is "a few unknowns wide"
SPOT = 2.5  # the spot: the pixels within this many core radii of the core
SPOT_SHARE = 0.5  # ... holding at least this share of the pose's χ² excess


@dataclass(frozen=True)
class SharpPeak:
    """The brightest spot's core against the fit: its pixels, the light beyond the fit there
    (a share of the fit's, and in standard errors), the pixels one unit of the unknowns covers
    there, and the pose's χ² per pixel."""

    core_px: int
    excess: float
    z: float
    negative: float  # the core's light where the fit is above the image, over where it is below
    unit_px: float
    chi2_per_pixel: float
    spot_share: float = float("nan")  # the share of the pose's χ² excess in the brightest spot (:data:`SPOT`)

    @property
    def seen(self) -> bool:
        return bool(np.isfinite(self.chi2_per_pixel) and self.chi2_per_pixel > CHI2_MAX and self.excess > MIN_EXCESS
                    and self.z > MIN_Z and self.negative <= MAX_NEGATIVE and 0 < self.core_px < self.unit_px)

    @property
    def near(self) -> bool:
        """Not :attr:`seen`, but the misfit lies mostly in a spot only a few unknowns wide: the
        unknowns are one reading of it, a camera model that does not match the images another
        (:func:`near_note`)."""
        return bool(not self.seen and np.isfinite(self.chi2_per_pixel) and self.chi2_per_pixel > CHI2_MAX
                    and self.unit_px > 0 and 0 < self.core_px < NEAR_UNITS * self.unit_px
                    and self.spot_share >= SPOT_SHARE)


def sharp_peak(measured, fitted, valid, variance, T, power, unknowns_per_element: float = 1.0,
               chi2_per_pixel: float = float("nan")) -> SharpPeak | None:
    """The test on one pose: ``measured``, ``fitted``, ``valid``, ``variance`` (ny, nx) photons,
    photons, bool, photons²; ``T`` (pixels x elements, the pose's views together) and ``power``
    (photons per element, NaN where not solved); ``unknowns_per_element``: the solve's unknowns
    over the elements.  None where there is no spot to test (no lit, valid pixel)."""
    m = np.asarray(measured, float)
    f = np.asarray(fitted, float)
    var = np.asarray(variance, float)
    ok = np.asarray(valid, bool) & np.isfinite(m) & np.isfinite(f) & (f >= 1.0) & (var > 0)
    if m.ndim != 2 or ok.sum() < 9:
        return None
    smooth = ndimage.uniform_filter(np.where(ok, m, 0.0), 3)
    top = smooth[ok].max()
    if not top > 0:
        return None
    core = ok & (smooth >= HALF * top)
    fit_core = float(f[core].sum())
    excess = float(m[core].sum()) - fit_core
    z = excess / float(np.sqrt(var[core].sum()))
    r = m[core] - f[core]
    negative = float(-r[r < 0].sum() / r[r > 0].sum()) if np.any(r > 0) else float("inf")
    b = np.nan_to_num(np.asarray(power, float))
    lit = np.asarray(T[np.flatnonzero(core.ravel())].sum(axis=0)).ravel() * b
    if not lit.max() > 0:
        return None
    col = np.asarray(T[:, int(np.argmax(lit))].todense() if hasattr(T, "todense") else T[:, int(np.argmax(lit))],
                     float).ravel()
    unit = float(col.sum() ** 2 / np.sum(col ** 2)) / max(float(unknowns_per_element), 1e-12) if np.any(col > 0) else 0.0
    return SharpPeak(int(core.sum()), excess / fit_core if fit_core > 0 else float("inf"), float(z), negative, unit,
                     float(chi2_per_pixel), _spot_share(m, f, var, ok, core))


def _spot_share(m, f, var, ok, core) -> float:
    """The share of the image's χ² excess (Σ (m − f)²/var − pixels) that lies in the brightest
    spot: the valid pixels within :data:`SPOT` core radii of its core (the core's radius that of a
    disc of its area; a Gaussian's light lies within 2.9 σ of its peak, its core's radius is
    1.18 σ), so that a bright background around the spot is not counted as the spot.  NaN when
    the image holds no excess."""
    radius = SPOT * float(np.sqrt(core.sum() / np.pi))
    spot = ok & (ndimage.distance_transform_edt(~core) <= radius)
    c = np.where(ok, (m - f) ** 2 / np.where(ok, var, 1.0), 0.0)
    total = float(c.sum()) - float(ok.sum())
    if not total > 0:
        return float("nan")
    return float(np.clip((float(c[spot].sum()) - float(spot.sum())) / total, 0.0, 1.0))


def _next_split(refine_faces: int) -> int:
    """The level of ``subject.refine_faces`` after the one the run used: what both notes name."""
    return int(refine_faces) + 1


def peak_warning(p: SharpPeak, refine_faces: int = 0) -> str:
    """The warning, naming the next level of ``subject.refine_faces`` (the one the run used: ``refine_faces``)."""
    nxt = _next_split(refine_faces)
    return (f"the light peaks more sharply than the surface's unknowns can follow: the images hold {p.excess:.0%} more "
            f"light than the fit in the {p.core_px} pixels of the brightest spot's half-maximum ({p.z:.0f} standard "
            f"errors), where the fit's unknowns cannot put light into fewer than about {p.unit_px:.0f} pixels (an element's "
            "footprint over its unknowns). "
            f"That is where chi^2 per pixel {p.chi2_per_pixel:.3g} comes from, not from the camera's pose or the "
            "emission model. The fit spreads the peak's light over the elements around it: the total is little "
            "affected, the map within an element or two of the peak is wrong. Split the faces (subject.refine_faces: "
            f"{nxt} splits each into {4 ** nxt}, and build-T's work grows about as much; the elements, what is reported, "
            "stay as they are) or give a finer mesh. A lens that blurs less than system.camera.lens says, or a small bright "
            "reflection or stray light in the image, would read the same way.")


def near_note(p: SharpPeak, refine_faces: int = 0) -> str:
    """What a pose's χ² warning adds when the misfit lies in a spot a few unknowns wide (:attr:`SharpPeak.near`):
    both readings, and the test that tells them apart (the next ``subject.refine_faces``)."""
    return (f" Most of this misfit ({p.spot_share:.0%} of chi^2's excess over the pixels) lies in the brightest spot, "
            f"whose half-maximum ({p.core_px} pixels) spans only about {p.core_px / p.unit_px:.1f} of the unknowns' "
            f"footprints ({p.unit_px:.0f} pixels each): light that varies within an element faster than the unknowns "
            "can follow misfits this way with a set-up that is right, and so does a camera model that does not match "
            f"the images. To tell them apart, split the faces (subject.refine_faces: {_next_split(refine_faces)}): if chi^2 "
            "falls, it was the unknowns.")


EXPLAINED = ("chi^2 per pixel is ", "the fit's residual is structured by viewing angle")  # what the peak explains


def with_peak_warnings(per_pose, peaks, refine_faces: int = 0) -> tuple[list, list[bool], list[bool]]:
    """Each pose's result with the peak's warning in place of the χ² and viewing-angle warnings it
    explains (:data:`EXPLAINED`), or with :func:`near_note` after its χ² warning; per pose whether
    the peak's warning fired (the shift test is then not asked: a peak the fit cannot reach reads
    as a shift too), and whether the note was added."""
    out, fired, near = [], [], []
    for (r, fitted), p in zip(per_pose, peaks):
        seen = p is not None and p.seen
        fired.append(seen)
        if seen:
            kept = tuple(w for w in r.warnings if not str(w).startswith(EXPLAINED))
            r = replace(r, warnings=(peak_warning(p, refine_faces),) + kept)
        elif p is not None and p.near:  # one reading among two: said after the χ² warning, which stays
            r = replace(r, warnings=tuple(_then(w, near_note(p, refine_faces)) if str(w).startswith(EXPLAINED[0]) else w
                                          for w in r.warnings))
        near.append(bool(not seen and p is not None and p.near))
        out.append((r, fitted))
    return out, fired, near


def _then(warning, note: str) -> str:
    """``warning`` as one sentence, then ``note`` (which starts with a space)."""
    w = str(warning).rstrip()
    return w + ("" if w.endswith(".") else ".") + note


def check_poses(per_pose, images, valid, noise, Ts, unknowns_per_element: float, refine_faces: int = 0
                 ) -> tuple[list, list[bool], list[bool]]:
    """:func:`sharp_peak` on each pose's fit (``per_pose``: [(Result, fitted image)]; ``images``,
    ``valid``: [pose, ny, nx]; ``noise``: the noise model; ``Ts``: each pose's T over the elements;
    ``refine_faces``: the run's subject.refine_faces), then :func:`with_peak_warnings`."""
    peaks = []
    for k, (r, fitted) in enumerate(per_pose):
        fit = np.where(np.isfinite(fitted), np.maximum(fitted, 0.0), 0.0)
        peaks.append(sharp_peak(images[k], fitted, valid[k], noise.variance(fit), Ts[k], r.power,
                                unknowns_per_element, r.chi2_per_pixel))
    return with_peak_warnings(per_pose, peaks, refine_faces)


def explain_joint(joint, fired: list[bool], labels: list[str], near: list[bool] | None = None):
    """The joint solve's result with its χ² and viewing-angle warnings (:data:`EXPLAINED`) replaced by
    one that points at the poses whose peak is sharper than the unknowns (``fired``, per pose with
    its ``labels``): their images are in the joint fit too.  Where none fired but some pose's misfit
    lies in a spot a few unknowns wide (``near``), its χ² warning stays and names those poses.
    ``joint`` unchanged when neither (or there is no joint solve)."""
    if joint is None:
        return joint
    if not any(fired):
        if not any(near or ()):
            return joint
        named = ", ".join(lab for lab, n in zip(labels, near) if n)
        note = (f" The misfit of pose(s) {named} lies mostly in a spot only a few unknowns wide (see their warnings): "
                "split the faces (subject.refine_faces) to tell the unknowns from the camera.")
        return replace(joint, warnings=tuple(_then(w, note) if str(w).startswith(EXPLAINED[0]) else w
                                             for w in joint.warnings))
    named = ", ".join(lab for lab, f in zip(labels, fired) if f)
    kept = tuple(w for w in joint.warnings if not str(w).startswith(EXPLAINED))
    note = (f"chi^2 per pixel is {joint.chi2_per_pixel:.3g}: the images of pose(s) {named} peak more sharply than the "
            "surface's unknowns can follow (see their warnings: split the faces with subject.refine_faces), and the "
            "joint fit holds those images too")
    return replace(joint, warnings=(note,) + kept)
