"""Knowing when the emission model matters (issue 21, item 2): how much of the observed light
was seen at grazing angles, and whether the fit's residual is structured by viewing angle.

Emission angles come from the surface's geometry, not from the rays: per view and face, the
angle between the face's outward normal and the line from its centroid to the (real or, for a
mirror view, virtual) lens centre, which is the direction of the real ray leaving the face.
Over the lens the angle varies by about atan(R / distance) (~1.5 deg for a 17 mm aperture at
317 mm), well inside the 15 deg bands used here.  An element's column is split between angle
bands by its faces' projected areas times the profile's weight (what each face sends to the
lens, occlusion within the element neglected).

Arrays and numbers only (no config, no printing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

BANDS_DEG = (60.0, 75.0)
# A warning when more than this share of a total rests on elements seen beyond 75 deg.  There
# the emission model is least certain even when it is the right one: diffuse(1.40) falls by
# ~5 % per degree at 80 deg, so a mesh normal off by 2-3 deg (a captured surface, a faceted
# phantom) moves an element's value by 10-15 %, and diffusion theory itself is 2-4 % off the
# Monte Carlo photons there; Lambertian and diffuse differ by 20-60 % (75-85 deg).  With 25 %
# of the total resting there, a 15-20 % error moves the total by 4-5 %, the error budget of a
# reconstruction.  The share is computed with the model's own b: a wrong model that underrates
# grazing light (Lambertian on tissue) understates it too.
GRAZING_SHARE_WARN = 0.25
# The residual test warns only when the trend is both significant and large enough to matter:
# |t| > 4 happens by chance in ~1 fit in 16000 (the t uses the chi-square-inflated error, so it is
# conservative when the misfit has other causes too); 3 % is below what a wrong profile gives.
STRUCTURE_T_WARN = 4.0
STRUCTURE_EFFECT_WARN = 0.03  # relative residual change across the observed angle range


def face_emission_cos(surface, center_mm: np.ndarray) -> np.ndarray:
    """Cosine of the angle between each face's normal and the line from its centroid to
    ``center_mm`` (a lens centre; for a mirror view the virtual one), shape (F,)."""
    cen = surface.face_vertices_mm.mean(axis=1)
    d = np.asarray(center_mm, float) - cen
    return np.einsum("ij,ij->i", surface.face_normals, d) / np.linalg.norm(d, axis=1)


@dataclass
class ElementAngles:
    """Per view and element: the power-weighted mean emission angle (deg, NaN when no face of
    the element faces the lens) and the fraction of what it sends beyond each band."""

    mean_deg: np.ndarray  # (V, E)
    beyond: np.ndarray  # (V, E, len(BANDS_DEG))


def element_angles(surface, centers_mm: list[np.ndarray], weight=None) -> ElementAngles:
    """:class:`ElementAngles` of ``surface`` for lens centres ``centers_mm`` (one per view);
    ``weight(cos)`` is the emission profile's ray weight (default Lambertian)."""
    eof = surface.element_of_face
    ok_face = eof >= 0
    n_el = surface.n_elements
    V = len(centers_mm)
    mean = np.full((V, n_el), np.nan)
    beyond = np.zeros((V, n_el, len(BANDS_DEG)))
    area = surface.face_areas_mm2
    for v, c in enumerate(centers_mm):
        cs = face_emission_cos(surface, c)
        front = ok_face & (cs > 0)
        w_profile = weight(np.clip(cs, 0, 1)) if weight is not None else 1.0
        w = np.where(front, area * np.clip(cs, 0, None) * w_profile, 0.0)
        e = np.where(ok_face, eof, 0)
        tot = np.bincount(e, weights=w, minlength=n_el)
        deg = np.degrees(np.arccos(np.clip(cs, -1, 1)))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[v] = np.where(tot > 0, np.bincount(e, weights=w * np.where(front, deg, 0.0), minlength=n_el) / tot,
                               np.nan)
            for b, lim in enumerate(BANDS_DEG):
                beyond[v, :, b] = np.where(tot > 0, np.bincount(e, weights=w * (deg > lim), minlength=n_el) / tot, 0.0)
    return ElementAngles(mean, beyond)


def best_view_deg(surface, cameras: list, T_views: list[sp.spmatrix]) -> np.ndarray:
    """Per element, the smallest angle (deg) from a face's outward normal at which a view that
    collects the element's light (its column of that view's T is not empty) can see it: over
    each view's aperture, towards the point of the lens disk farthest along the face normal
    (``cameras``: one per view, the virtual one for a mirror view). inf where no view collects
    its light. A lens not small beside its distance sees a face turned edge-on to its
    centre through part of its disk: the centre alone would put that face behind the lens."""
    eof = surface.element_of_face
    ok = eof >= 0
    cen = surface.face_vertices_mm.mean(axis=1)
    nrm = surface.face_normals
    best = np.full(surface.n_elements, np.inf)
    for cam, Tv in zip(cameras, T_views):
        seen = np.asarray(abs(Tv).sum(axis=0)).ravel() > 0
        a = np.asarray(cam.axis, float) / np.linalg.norm(cam.axis)
        w = nrm - (nrm @ a)[:, None] * a
        wl = np.linalg.norm(w, axis=1)
        w = np.where(wl[:, None] > 1e-12, w / np.maximum(wl, 1e-300)[:, None], 0.0)
        d = cam.center_mm + cam.aperture_radius_mm * w - cen
        cs = np.einsum("ij,ij->i", nrm, d) / np.linalg.norm(d, axis=1)
        deg = np.degrees(np.arccos(np.clip(cs, -1.0, 1.0)))
        el = np.full(surface.n_elements, np.inf)
        np.minimum.at(el, eof[ok], deg[ok])
        best = np.where(seen, np.minimum(best, el), best)
    return best


EDGE_ON_TEXT = "seen only beyond"


def leave_out_edge_on(res, best_deg: np.ndarray, limit_deg: float, model: str):
    """``res`` (an :class:`fluxcli.inverse.Result` over elements) with the observed elements
    seen only beyond ``limit_deg`` from their normal (``best_deg`` > limit) made unobserved
    (power and sigma NaN): they were solved for, so the light they sent is theirs and not
    their neighbours', but their values rest on views where that light is the most sensitive
    to the normal and to the emission model, and they leave the observed total. A warning says how many and what share of the total they
    held. ``res`` unchanged when none (or ``limit_deg`` >= 90)."""
    from dataclasses import replace

    if limit_deg >= 90.0 or res is None:
        return res
    obs = np.asarray(res.observed, bool)
    cut = obs & (np.asarray(best_deg) > limit_deg)
    if not cut.any():
        return res
    p = np.asarray(res.power, float)
    total = np.nansum(np.where(obs, p, 0.0))
    share = np.nansum(np.where(cut, p, 0.0)) / total if total > 0 else float("nan")
    observation = None if res.observation is None else np.where(cut, 0, res.observation).astype(np.int8)
    warning = (f"{int(cut.sum())} element(s) {EDGE_ON_TEXT} {limit_deg:g} deg from their normal (edge-on; "
               f"{share:.0%} of the total as solved) are solved for, so their light is their own, but are left out "
               f"of the observed total: their values rest on views where the light an element sends is the most "
               f"sensitive to its normal and to the emission model ({model}).")
    from .methods import POOR_SHARE_TEXT, poor_share_warning

    power, observed = np.where(cut, np.nan, p), obs & ~cut
    warnings = [w for w in res.warnings if POOR_SHARE_TEXT not in w]  # its share was of the old total
    if observation is not None and (poor := poor_share_warning(power, observed, observation)):
        warnings.append(poor)
    return replace(res, power=power, observed=observed, sigma=np.where(cut, np.nan, np.asarray(res.sigma, float)),
                   observation=observation, warnings=tuple(warnings) + (warning,))


def grazing_shares(T_views: list[sp.spmatrix], view_weights: list[float], power: np.ndarray,
                   angles: ElementAngles) -> np.ndarray:
    """Share of the light in the model image ``sum_v w_v T_v b`` that left its element beyond
    each band angle (len(BANDS_DEG),); NaN when the model image is dark."""
    b = np.nan_to_num(np.asarray(power, float), nan=0.0)
    b = np.clip(b, 0.0, None)
    tot = 0.0
    beyond = np.zeros(len(BANDS_DEG))
    for v, (Tv, wv) in enumerate(zip(T_views, view_weights)):
        seen = wv * np.asarray(Tv.sum(axis=0)).ravel() * b  # per element, photons reaching the sensor
        tot += seen.sum()
        beyond += seen @ angles.beyond[v]
    return beyond / tot if tot > 0 else np.full(len(BANDS_DEG), np.nan)


def total_shares(T_views: list[sp.spmatrix], view_weights: list[float], power: np.ndarray,
                 angles: ElementAngles) -> np.ndarray:
    """Share of the reconstructed total ``sum_j b_j`` that rests on grazing views: each element's
    power weighted by the fraction of its collected light (all views) that left it beyond each
    band angle, (len(BANDS_DEG),).  An element seen only at 80 deg counts whole: its value comes
    from the emission model at 80 deg alone, however little light reached the camera."""
    b = np.clip(np.nan_to_num(np.asarray(power, float), nan=0.0), 0.0, None)
    seen = np.zeros(len(b))
    beyond = np.zeros((len(b), len(BANDS_DEG)))
    for v, (Tv, wv) in enumerate(zip(T_views, view_weights)):
        col = wv * np.asarray(Tv.sum(axis=0)).ravel()
        seen += col
        beyond += col[:, None] * angles.beyond[v]
    ok = seen > 0
    tot = b[ok].sum()
    if not tot > 0:
        return np.full(len(BANDS_DEG), np.nan)
    return (b[ok] @ (beyond[ok] / seen[ok, None])) / tot


def pixel_angles(T_views: list[sp.spmatrix], view_weights: list[float], power: np.ndarray,
                 angles: ElementAngles) -> np.ndarray:
    """Per pixel, the mean emission angle (deg) of the light the model image puts there
    (weighted by that light); NaN where the model is dark."""
    b = np.clip(np.nan_to_num(np.asarray(power, float), nan=0.0), 0.0, None)
    num = 0.0
    den = 0.0
    for v, (Tv, wv) in enumerate(zip(T_views, view_weights)):
        th = np.nan_to_num(angles.mean_deg[v], nan=0.0)
        num = num + wv * (Tv @ (b * th))
        den = den + wv * (Tv @ b)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


@dataclass
class AngleStructure:
    """A weighted regression of the relative residual (measured - model) / model on the pixel's
    emission angle: ``slope_per_10deg`` (relative), its t value, the change across the 10th-90th
    percentile of the angles (``effect``, relative), that range (deg) and the pixels used."""

    slope_per_10deg: float
    t: float
    effect: float
    range_deg: tuple[float, float]
    n_pixels: int

    @property
    def significant(self) -> bool:
        return abs(self.t) > STRUCTURE_T_WARN and abs(self.effect) > STRUCTURE_EFFECT_WARN


def angle_structure(measured: np.ndarray, model: np.ndarray, variance: np.ndarray, angle_deg: np.ndarray,
                    valid: np.ndarray | None = None) -> AngleStructure | None:
    """Is the residual structured by viewing angle?  Relative residuals ``e = (a - m) / m`` with
    weights ``m^2 / var`` (their inverse variance) regressed on the angle; the slope's standard
    error is inflated by the reduced chi-square when above 1, so that misfit not tied to the angle
    (regularisation, a wrong noise model) does not read as structure.  None when too few pixels
    or angles are too alike to test."""
    a, m, var, x = (np.asarray(z, float).ravel() for z in (measured, model, variance, angle_deg))
    ok = np.isfinite(a) & np.isfinite(m) & np.isfinite(var) & np.isfinite(x) & (m > 0) & (var > 0)
    if valid is not None:
        ok &= np.asarray(valid, bool).ravel()
    if ok.sum() < 10:
        return None
    a, m, var, x = a[ok], m[ok], var[ok], x[ok]
    e = (a - m) / m
    w = m * m / var
    if not (np.isfinite(w.sum()) and w.sum() > 0):  # weights that overflow (absurd signals): no test
        return None
    order = np.argsort(x)
    cw = np.cumsum(w[order]) / w.sum()
    lo, hi = float(x[order][np.searchsorted(cw, 0.1)]), float(x[order][min(np.searchsorted(cw, 0.9), len(x) - 1)])
    if hi - lo < 2.0:  # all the light seen from about one angle: nothing to regress on
        return None
    xm = np.sum(w * x) / w.sum()
    em = np.sum(w * e) / w.sum()
    sxx = np.sum(w * (x - xm) ** 2)
    beta = np.sum(w * (x - xm) * (e - em)) / sxx
    resid = e - em - beta * (x - xm)
    chi2_red = max(1.0, float(np.sum(w * resid**2)) / max(len(x) - 2, 1))
    se = np.sqrt(chi2_red / sxx)
    return AngleStructure(float(10 * beta), float(beta / se), float(beta * (hi - lo)), (lo, hi), int(len(x)))


def describe_shares(shares: np.ndarray) -> str:
    if not np.isfinite(shares).any():  # no light to share out (images or a fit that hold none)
        return "none to share (no light)"
    return ", ".join((f"{s:.0%}" if np.isfinite(s) else "-") + f" beyond {b:g} deg" for s, b in zip(shares, BANDS_DEG))


# A surface whose faces meet at this much or more where it bends (the median crease between 2 and
# 45 deg) is a coarse faceting of a round body: its normals are up to half that off the body's,
# and diffuse light at 80 deg changes by ~5 % a degree.
COARSE_CREASE_DEG = 10.0


def median_crease_deg(surface) -> float:
    """The median angle (deg) between the normals of faces that share an edge, over the edges
    where the surface bends gently (2-45 deg: a faceted curve, not a box's edges, not a flat
    face's diagonals); NaN where it bends nowhere in that range."""
    f = np.asarray(surface.faces)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, inv, count = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(inv, kind="stable")
    shared = count[inv[order]] == 2
    a, b = face[order][shared][0::2], face[order][shared][1::2]
    nrm = surface.face_normals
    deg = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", nrm[a], nrm[b]), -1.0, 1.0)))
    bend = deg[(deg > 2.0) & (deg < 45.0)]
    return float(np.median(bend)) if len(bend) else float("nan")


def grazing_warning(total_shares: np.ndarray, crease_deg: float = float("nan")) -> str | None:
    """A warning when a large share of the total rests on views beyond 75 deg
    (:func:`total_shares`); ``crease_deg`` (:func:`median_crease_deg`) adds what a coarse
    faceting of a round body does there."""
    s75 = float(total_shares[BANDS_DEG.index(75.0)])
    if np.isfinite(s75) and s75 > GRAZING_SHARE_WARN:
        coarse = (f" The surface's faces meet at {crease_deg:.0f} deg where it bends (median): if the body is round "
                  f"there, their normals are up to {crease_deg / 2:.0f} deg off its own, which moves the light seen "
                  "at 80 deg by tens of per cent; a finer mesh, or subject.refine_faces: 1 on a round phantom "
                  "(its split faces follow the round body), models it better."
                  if np.isfinite(crease_deg) and crease_deg >= COARSE_CREASE_DEG else "")
        return (f"{s75:.0%} of the total rests on elements seen beyond 75 deg from their normal, where the emission "
                "model is least certain (Lambertian and diffuse differ by 20-35 % there): add a pose or a mirror "
                "that sees them more head-on, or check subject.emission." + coarse)
    return None


def structure_warning(st: AngleStructure | None, emission_name: str) -> str | None:
    if st is None or not st.significant:
        return None
    lo, hi = st.range_deg
    more = "more" if st.effect > 0 else "less"
    return (f"the fit's residual is structured by viewing angle: the images hold {abs(st.effect):.1%} {more} light "
            f"at {hi:.0f} deg from the normal than at {lo:.0f} deg, relative to the model (t = {st.t:.1f}); the "
            f"emission model ({emission_name}) may not describe this surface (subject.emission).")
