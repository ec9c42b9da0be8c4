"""Issue 21, item 2: how much of a reconstruction rests on grazing views, and whether its
residual is structured by viewing angle (:mod:`fluxcli.inverse.diagnostics`).

Per pose (and jointly) the share of the observed light seen beyond 60 and 75 deg from the
normal and the share of the total resting on such views; the warnings are added to the
poses' results (and the joint solve's).  T per view is read from each pose's T cache file.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..artefacts.reconstruction import Emission
from ..artefacts.transfer import load_view
from ..optics.emission import CHECK_DEG
from . import diagnostics as D


def emission_checks(profile, views, todo, per_pose, joint, images, valid, noise, mismatch: str | None = None
                    ) -> tuple[list, object, list[str], Emission, list[bool]]:
    """``profile``: the emission model; ``views``: the camera views; ``todo``: per pose (placed
    scene, T plan); ``per_pose``: [(Result, fitted image)]; ``images``/``valid``: [pose, ny, nx];
    ``mismatch``: a warning for the first pose (images simulated under another emission model).
    Returns the poses and joint result with the warnings added, the console lines, the record, and
    per pose whether its residual is structured by viewing angle (the shift test's warning uses it)."""
    prof = profile
    deg = np.linspace(0.0, 90.0, 181)
    weights = [v.weight for v in views]
    centres = [v.camera.center_mm for v in views]
    light, totals, slopes, out, all_T, all_ang, structured = [], [], [], [], [], [], []
    crease = D.median_crease_deg(todo[0][0].surface) if todo else float("nan")  # the same surface in every pose
    for k, ((res, fitted), (scene, pt)) in enumerate(zip(per_pose, todo)):
        Tv = [load_view(pt.path, v) for v in range(len(views))]
        ang = D.element_angles(scene.surface, centres, prof.weight)
        light.append(D.grazing_shares(Tv, weights, res.power, ang))
        totals.append(D.total_shares(Tv, weights, res.power, ang))
        px = D.pixel_angles(Tv, weights, res.power, ang)
        model = np.nan_to_num(fitted.ravel())
        st = D.angle_structure(images[k].ravel(), model, noise.variance(model), px, valid[k].ravel())
        warns = tuple(w for w in (D.grazing_warning(totals[-1], crease), D.structure_warning(st, prof.describe()),
                                  mismatch if k == 0 else None) if w)
        out.append((replace(res, warnings=tuple(res.warnings) + warns), fitted) if warns else (res, fitted))
        slopes.append([np.nan, np.nan] if st is None else [st.slope_per_10deg, st.t])
        structured.append(st is not None and st.significant)
        if joint is not None:
            all_T += Tv
            all_ang.append(ang)
    record = Emission(prof.model, prof.describe(), np.nan if prof.refractive_index is None else prof.refractive_index,
                      prof.source or "", deg, prof.radiance(np.radians(deg)), np.array(D.BANDS_DEG), np.array(light),
                      np.array(totals), np.array(slopes))
    lines = [f"emission model: {prof.describe()}"
             + ("" if prof.is_lambertian else " (L/L0 " + ", ".join(
                 f"{r:.2f} at {a:g} deg" for a, r in zip(CHECK_DEG[::2], prof.radiance(np.radians(CHECK_DEG[::2]))))
                + ")")]
    if prof.body_curvature and todo:
        lines.append(body_curvature_line(todo[0][0].surface, views, prof))
    lines += [f"seen at grazing angles, pose {pt.pose.label}: light {D.describe_shares(li)}; "
              f"total {D.describe_shares(to)}" for li, to, (_, pt) in zip(light, totals, todo)]
    if joint is not None:
        ang = D.ElementAngles(np.concatenate([a.mean_deg for a in all_ang]), np.concatenate([a.beyond for a in all_ang]))
        jl = D.grazing_shares(all_T, weights * len(todo), joint.power, ang)
        jt = D.total_shares(all_T, weights * len(todo), joint.power, ang)
        record.joint_light_beyond_deg, record.joint_total_beyond_deg = jl, jt
        lines.append(f"seen at grazing angles, all poses jointly: light {D.describe_shares(jl)}; "
                     f"total {D.describe_shares(jt)}")
        w = D.grazing_warning(jt, crease)
        if w:
            joint = replace(joint, warnings=tuple(joint.warnings) + (w,))
    return out, joint, lines, record, structured


def body_curvature_line(surface, views, prof) -> str:
    """One console line on the body's curvature (:mod:`fluxcli.optics.body_curvature`): the mean
    curvature the mesh gives its elements and how far it bends their light towards the views."""
    from ..optics.body_curvature import fit_radius_mm, mean_curvature, view_factors

    transport = prof.reduced_scattering_per_mm + prof.absorption_per_mm
    H = mean_curvature(surface, fit_radius_mm(surface, transport))
    fac = np.concatenate(view_factors(surface, views, prof))
    if not np.any(H != 0):
        return "body curvature: the mesh is flat everywhere (mean curvature 0): the profile is not bent"
    lo, med, hi = np.percentile(H, [5, 50, 95])
    return (f"body curvature: mean curvature {lo:.3g} .. {hi:.3g} /mm over the elements (5-95 %, median {med:.3g}; "
            f"a sphere of radius {1 / med:.0f} mm has the median)" if med > 0 else
            f"body curvature: mean curvature {lo:.3g} .. {hi:.3g} /mm over the elements (5-95 %, median {med:.3g})") + \
        f"; the light each element sends towards the views x{fac.min():.3f} .. x{fac.max():.3f}"


def photons_medium_note(flux: dict, now: dict | None) -> str | None:
    """A warning when Monte Carlo photons (``flux``: simulate.flux as the simulation recorded it)
    are reconstructed with a ``diffuse`` model (``now``: subject.emission as the geometry records
    it) told another medium than the one the photons went through: refractive index, anisotropy g
    (``scattering_anisotropy``), or mu_a and mu_s' (as the depth term's c = 3 mu_a / mu_t' and the
    transport coefficient mu_t' the key holds).  A model-mismatch experiment can be the point; a
    forgotten key usually is not (tissue's g 0.9 read as isotropic: the drift a fifth too long,
    docs/accuracy.md §1.1).  None when they agree, or the model is not ``diffuse``."""
    if not isinstance(now, dict) or now.get("model") != "diffuse" or not isinstance(flux, dict):
        return None
    try:
        n, g = float(flux["refractive_index"]), float(flux.get("g", 0.0))
        mua, musp = float(flux["mua_per_mm"]), float(flux["mus_per_mm"]) * (1.0 - float(flux.get("g", 0.0)))
    except (KeyError, TypeError, ValueError):
        return None
    told, given = [], []
    if abs(float(now.get("refractive_index", n)) - n) > 1e-6:
        told.append(f"refractive index {float(now['refractive_index']):g}")
        given.append(f"{n:g}")
    uses_medium = any(k in now for k in ("depth_term", "tangent_sha256", "body_curvature", "curvature_sha256"))
    g_now = float(now.get("scattering_anisotropy", 0.0))
    if uses_medium and abs(g_now - g) > 0.005:
        told.append(f"g {g_now:g} (scattering_anisotropy)")
        given.append(f"g {g:g}")
    c_now, t_now = now.get("depth_term"), now.get("transport_per_mm")
    if (c_now is not None and abs(float(c_now) - 3 * mua / (mua + musp)) > 0.02 * 3 * mua / (mua + musp) + 1e-9) or (
            t_now is not None and abs(float(t_now) - (mua + musp)) > 0.02 * (mua + musp)):
        told.append("another mu_a or mu_s' (absorption_per_mm, reduced_scattering_per_mm)")
        given.append(f"mu_a {mua:g} /mm, mu_s' {musp:g} /mm")
    if not told:
        return None
    return (f"the photons went through a medium of {', '.join(given)} (simulate.flux), but subject.emission "
            f"describes {', '.join(told)}: a model-mismatch experiment, unless subject.emission was meant to "
            "describe the photons' medium (then give it the same numbers)")

