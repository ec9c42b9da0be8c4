"""One solve as reconstruct runs it: the method settings, the noise model, the unknowns.

:func:`run_method` solves on the valid pixels and maps the unknowns back to the elements;
:func:`solve_poses` runs each pose (isolated spikes left out and solved again) and all poses
jointly; :func:`describe` names a setting.  Method settings are
:class:`fluxcli.config.MethodSettings`-like (method, lam, lambda_rule, max_iter, tol, n_iter,
unknowns).
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from ..errors import InputError, UserError
from ..imaging import noise as N
from ..imaging.spikes import reject_spikes
from ..workers import blas_threads
from .methods import REGISTRY, solver_options
from .methods import reconstruct as _reconstruct
from .unknowns import ElementMap, element_unknowns, on_elements

REGULARISED = tuple(n for n, s in REGISTRY.items() if s.lam_rules)  # take reconstruct.lambda / lambda_rule
DENSE = tuple(n for n, s in REGISTRY.items() if s.dense)  # form T'WT (n x n) densely


def run_method(T: sp.csr_matrix, a: np.ndarray, valid: np.ndarray, m, noise: N.PhotonNoise,
               adjacency=None, parent=None, n_elements: int | None = None, areas=None):
    """Solve on the valid pixels; returns the inverse.Result and the pixel mask used.

    ``noise`` is the images' noise model; ``adjacency`` (unknowns touching) and ``areas``
    (mm²) are what the exitance prior of ``smooth`` needs; with ``parent`` the unknowns are
    sub-elements, summed back into ``n_elements`` elements (an element counts as observed
    when any of its parts is, its class is its best part's; sigma is not propagated: NaN);
    with an :class:`ElementMap` they are vertices shared out to the elements, which are
    classified on their own T."""
    if isinstance(parent, ElementMap) and parent.hats is not None:
        T, parent, adjacency, areas = element_unknowns(T, valid, parent)
    with blas_threads(1):  # dense ~10^3 solves: BLAS threads cost more than they give (workers.blas_threads)
        groups = parent.to_elements if isinstance(parent, ElementMap) else (
            None if parent is None else (parent, n_elements))
        res, keep = _solve(T, a, valid, m, noise, adjacency, areas, groups=groups)
    if parent is None:
        return res, keep
    from ..inverse.covariance import Mapped, parent_map

    if res.covariance is not None:  # variance_of(weights over the elements) (ROI totals)
        res = replace(res, covariance=Mapped(res.covariance, parent.to_elements if isinstance(parent, ElementMap)
                                             else parent_map(parent, n_elements)))
    if isinstance(parent, ElementMap):
        return on_elements(res, keep, parent), keep
    obs = res.observed
    power = np.bincount(parent, weights=np.where(obs, res.power, 0.0), minlength=n_elements)
    observed = np.bincount(parent, weights=obs.astype(float), minlength=n_elements) > 0
    cls = np.zeros(n_elements, np.int8)
    np.maximum.at(cls, parent, res.observation)
    sigma = res.sigma_groups if res.sigma_groups is not None else np.full(n_elements, np.nan)
    return replace(res, power=np.where(observed, power, np.nan), observed=observed,
                   sigma=np.where(observed, sigma, np.nan), observation=cls), keep



def _solve(T, a, valid, m, noise, adjacency, areas, groups=None):
    keep = valid.ravel()
    Tm, am = T[keep], a.ravel()[keep]
    if REGISTRY[m.method].nonnegative_data:  # Poisson likelihood: bias-subtracted counts can dip below zero
        am = np.maximum(am, 0.0)
    kw = solver_options(m.method, m)  # the registry says which settings each method takes
    try:
        return _reconstruct(Tm, am, method=m.method, variance=noise.variance, adjacency=adjacency, areas=areas,
                     groups=groups, **kw), keep
    except InputError as e:  # say it in config keys, not the solver's parameter names
        msg = str(e)
        for internal, key in (("lam_rule", "reconstruct.lambda_rule"), ("lam", "reconstruct.lambda"),
                              ("n_iter", "reconstruct.n_iter"), ("transfer matrix T", "T")):
            msg = re.sub(rf"\b{internal}\b", key, msg)
        raise UserError(f"reconstruct.method {m.method}: {msg}") from None


def solve_poses(gm, inp, m, noise, stray, todo, shape, joint_too: bool, rois, scale: float = 1.0, what: str = ""):
    """Each pose on its own (isolated spikes left out and solved again), then all jointly;
    every region of interest measured on each result while its covariance is alive.
    ``scale`` divides the results (a filter's transmission: the light before the filter);
    ``what`` follows a pose's name in an error (``" (filter 580nm)"``).
    Returns [(Result, fitted image)] per pose and the joint Result (or None)."""
    ny, nx = shape
    P = len(todo)
    per_pose = []
    for k in range(P):
        seen = np.asarray(abs(gm.Ts[k]).sum(axis=1)).ravel() > 0
        if not np.any(seen & np.asarray(inp.valid[k], bool).ravel()):
            raise UserError(f"reconstruct, pose {todo[k][1].pose.label}{what}: none of the {int(seen.sum())} pixels that "
                            "see the subject is usable (each is saturated, NaN or masked), so there is nothing to "
                            "reconstruct from; take the images again with a shorter exposure or a lower EM gain.")
        def solve_pose(T=None):  # T: pose k's T bent by the curvature term (None: gm's)
            res, keep = run_method(gm.Ts[k] if T is None else T, inp.images[k], inp.valid[k], m, noise,
                                   gm.adjacency, gm.parts(k), gm.n_elements, gm.areas)
            fitted = np.full(nx * ny, np.nan)
            fitted[keep] = res.fitted
            return res, fitted.reshape(ny, nx)
        res, fitted = solve_pose()
        # inp.valid[k] is a new view at every indexing: compare with the one reject_spikes was given
        # (`valid_k is not inp.valid[k]` was always true: every pose was solved twice)
        valid_before = inp.valid[k]
        valid_k, spiked = reject_spikes(inp.images[k], fitted, valid_before, noise)
        if valid_k is not valid_before:  # solved again without them; the joint solve leaves them out too
            inp.valid[k] = valid_k
            res, fitted = solve_pose()
        if gm.curvature is not None:  # the emission's curvature term: solved again, bent by this solution
            res, fitted = solve_pose(gm.curvature.T(k, res.power))
        turned = orientation_hint(lambda a, v: run_method(gm.Ts[k], a, v, m, noise, gm.adjacency, gm.parts(k),
                                                          gm.n_elements, gm.areas)[0].chi2_per_pixel,
                                  inp.images[k], inp.valid[k], res.chi2_per_pixel, gm.n_elements, seen.reshape(ny, nx))
        res = scaled(replace(res, warnings=tuple(w for w in (stray[k], spiked, turned) if w) + tuple(res.warnings)),
                     scale)
        if rois:
            rois.measure(str(k + 1), todo[k][1].pose.height_mm, todo[k][1].pose.rotation_deg, res)
        per_pose.append((replace(res, covariance=None), fitted))  # the covariance is n x n: measured, dropped
    joint = None
    if joint_too and P > 1:
        Tj = sp.vstack(gm.Ts).tocsr()
        joint, _ = run_method(Tj, inp.images, inp.valid, m, noise, gm.adjacency, gm.parts(),
                              gm.n_elements, gm.areas)
        if gm.curvature is not None:
            Tj = sp.vstack([gm.curvature.T(k, joint.power) for k in range(P)]).tocsr()
            joint, _ = run_method(Tj, inp.images, inp.valid, m, noise, gm.adjacency, gm.parts(),
                                  gm.n_elements, gm.areas)
        joint = scaled(joint, scale)
        if rois:
            rois.measure("joint", None, None, joint)
        joint = replace(joint, covariance=None)
    return per_pose, joint


ORIENTATIONS = (("upside down", lambda x: x[::-1]), ("mirrored left to right", lambda x: x[:, ::-1]),
                ("turned half a turn", lambda x: x[::-1, ::-1]), ("transposed", lambda x: x.T))
ORIENTATION_MAX_ELEMENTS = 5000  # four more solves of a pose that misfits: only where they are cheap
ORIENTATION_GAIN = 2.0
ORIENTATION_REACH = 0.02  # a turned image may put at most this much more of its light where the subject cannot be seen


def orientation_hint(chi2_of, image: np.ndarray, valid: np.ndarray, chi2: float, n_elements: int,
                     reach: np.ndarray | None = None) -> str | None:
    """A warning when a pose's image, which misfits (χ² per pixel above the range), fits at least
    2× better, and within the range, flipped, mirrored, turned or transposed: its row or column
    order is another program's (FITS stores rows bottom-up; some camera software mirrors). The
    image is used as given. ``chi2_of(image, valid)``: χ² per pixel of a solve of that pose.
    None: nothing to say. Without it an image upside down read 0.946× the truth under a warning
    that blamed the model.

    ``reach`` (ny, nx) bool: the pixels that see the subject (T's rows with an entry). χ² counts
    only the pixels the fit lights, so a turned image whose light falls where nothing can be seen
    "fits" by leaving that light out. Such a turning is not offered: it may put at most
    :data:`ORIENTATION_REACH` more of the image's light outside ``reach`` than the image as given.
    The demo's images with the lens 0.6 mm off the config's read "3.85x better turned half a turn"
    (χ² 1.12 against 4.32): turned, 44 % of the light lies outside the subject's reach (2.3 % as
    given)."""
    from .filtered import CHI2_RANGE

    if not np.isfinite(chi2) or chi2 <= CHI2_RANGE[1] or n_elements > ORIENTATION_MAX_ELEMENTS:
        return None
    out_given = _light_outside(image, valid, reach)
    best = None
    for name, turn in ORIENTATIONS:
        a = turn(np.asarray(image))
        if a.shape != np.shape(image):
            continue
        if _light_outside(a, turn(np.asarray(valid)), reach) > out_given + ORIENTATION_REACH:
            continue
        try:  # a diagnostic: a solve that cannot run on the turned image says nothing, and stops nothing
            c = chi2_of(np.ascontiguousarray(a), np.ascontiguousarray(turn(np.asarray(valid))))
        except (UserError, InputError, ValueError, np.linalg.LinAlgError):
            continue
        if np.isfinite(c) and (best is None or c < best[1]):
            best = (name, c)
    if best is None or best[1] * ORIENTATION_GAIN > chi2 or best[1] > CHI2_RANGE[1]:
        return None
    return (f"its image fits {chi2 / best[1]:.3g}x better {best[0]} (chi^2 per pixel {best[1]:.3g} against {chi2:.3g} as "
            "given): is its row or column order another program's (FITS stores rows bottom-up; some camera software "
            "mirrors or rotates)? The image is used as given; turn the file, not the config.")


def _light_outside(image, valid, reach) -> float:
    """The share of the image's light (its positive valid pixels) that lies outside ``reach``
    (0 without ``reach``, or where the image holds no light)."""
    if reach is None:
        return 0.0
    a = np.where(np.asarray(valid, bool) & np.isfinite(image), np.maximum(np.asarray(image, float), 0.0), 0.0)
    total = float(a.sum())
    return float(a[~np.asarray(reach, bool)].sum()) / total if total > 0 else 0.0


def scaled(res, scale: float):
    """The result divided by ``scale`` (power, σ; the covariance by scale²)."""
    if scale == 1.0:
        return res
    from ..inverse.covariance import Scaled

    return replace(res, power=res.power / scale, sigma=res.sigma / scale,
                   sigma_groups=None if res.sigma_groups is None else res.sigma_groups / scale,
                   covariance=None if res.covariance is None else Scaled(res.covariance, 1.0 / scale))



def describe(m) -> str:
    base = _describe(m)
    return {"elements": base, "vertices": f"{base} on vertices (exitance linear within faces)",
            "linear_elements": f"{base} per element, exitance linear within faces"}.get(
        m.unknowns, f"{base} on sub-elements")


def _describe(m) -> str:
    if m.method == "smooth":
        lam = ("auto/UPRE" if m.lambda_rule == "gcv" else f"auto/{m.lambda_rule}") if m.lam == "auto" else f"{m.lam:g}"
        return f"smooth(lambda={lam}, {m.max_iter} it)"
    if m.method in REGULARISED:
        lam = f"auto/{m.lambda_rule}" if m.lam == "auto" else f"{m.lam:g}"
        extra = f", {m.max_iter} it" if m.method == "paper" else ""
        return f"{m.method}(lambda={lam}{extra})"
    return f"{m.method}({m.n_iter} it)" if m.method == "mlem" else m.method


