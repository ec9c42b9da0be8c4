"""reconstruct's filters after the first, and the warnings every filter's solves give.

A capture through several emission filters is reconstructed filter by filter with one T per
pose (the filter changes the light, not the geometry).  Each filter after the first goes
through what the first goes through after its solve: the emission model's domain (edge-on
elements left out of the observed total, so that the filters' totals cover the same elements
and their ratio is a spectrum, not a geometry), the share of its total resting on grazing
views and a residual structured by viewing angle, the test for a peak sharper than the
unknowns, the dark-pose test, and every warning of its solves, named by filter, into the
artefact's /warnings and the console.  Before this the other filters' solves kept their
warnings to themselves (a reflection in one filter's frames, a filter that passed nothing:
exit 0 and not a word), and their totals held the edge-on elements the first filter's left
out.
"""

from __future__ import annotations

import numpy as np

from ..imaging.stray import light_outside
from ..inverse.emission_checks import emission_checks
from ..inverse.emission_domain import leave_out_edge_on
from ..inverse.filtered import poses_disagree
from ..inverse.sharp_peak import check_poses, explain_joint
from ..inverse.solve import solve_poses
from ._reconstruct_inputs import Inputs, from_capture, photon_noise
from .rois import RoiMeter


def noise_of(plan, inp: Inputs):
    """The images' noise model under the plan's ``reconstruct.noise``."""
    return photon_noise(plan.noise, plan.read_noise_photons, plan.images.sensor, inp.noise_kind, inp.exposure_s,
                        inp.frames_averaged)


def checked_solves(per_pose, joint, inp: Inputs, noise, Ts, unknowns_per_element: float, refine_faces: int, todo):
    """The sharp-peak test (:mod:`fluxcli.inverse.sharp_peak`) on each pose's solve and its note on
    the joint one: ``(per_pose, joint, fired)``."""
    per_pose, fired, near = check_poses(per_pose, inp.images, inp.valid, noise, Ts, unknowns_per_element, refine_faces)
    return per_pose, explain_joint(joint, fired, [pt.pose.label for _, pt in todo], near), fired


DARK_SIGMAS = 5.0  # light over the subject's pixels below this many standard errors of their noise: none


def dark_poses(inp: Inputs, todo, noise=None, Ts=None) -> list[str]:
    """A pose whose images hold no light: no valid pixel above 0, or (with the noise model
    ``noise`` and each pose's T, ``Ts``) no more over the pixels that see the subject than
    :data:`DARK_SIGMAS` standard errors of their noise (a bias frame, a filter that passes
    nothing, the light off).  Its total is 0 within the noise and what the fit says of it
    (the regularisation, the misfit) is about nothing, which the user should hear first."""
    out = []
    for k, (_, pt) in enumerate(todo):
        a = np.asarray(inp.images[k], float).ravel()
        use = np.asarray(inp.valid[k], bool).ravel() & np.isfinite(a)
        if Ts is not None:
            use &= np.asarray(abs(Ts[k]).sum(axis=1)).ravel() > 0
        light = float(a[use].sum())
        sd = float(np.sqrt(np.sum(noise.variance(np.maximum(a[use], 0.0))))) if noise is not None and use.any() else 0.0
        if np.any(a[use] > 0) and not (noise is not None and light <= DARK_SIGMAS * sd):
            continue
        what = ("no valid pixel above 0" if not np.any(a[use] > 0) else
                f"{light:.3g} photons over the {int(use.sum())} pixels that see the subject, against {sd:.3g} of noise")
        out.append(f"pose {pt.pose.label}: its images hold no light ({what}): its total is 0 within the noise "
                   "floor, and its warnings about the fit below say nothing about the subject; check the exposure, "
                   "the filter and that the subject is in view")
    return out


def solve_warnings(per_pose, joint, todo) -> list[str]:
    """Every warning of every solve (to the console and to /warnings: never silent)."""
    out = [f"pose {pt.pose.label}: {w}" for (r, _), (_, pt) in zip(per_pose, todo) for w in r.warnings]
    if joint is None:
        return out
    apart = poses_disagree([r.chi2_per_pixel for r, _ in per_pose], joint.chi2_per_pixel,
                           [np.nansum(r.power) for r, _ in per_pose], [pt.pose.label for _, pt in todo])
    return out + [f"joint: {w}" for w in joint.warnings] + ([f"joint: {apart}"] if apart else [])


def named(filters: list, name: str, warnings: list[str]) -> list[str]:
    """``warnings`` of filter ``name``, each naming it when the run has several filters."""
    return [f"filter {name}, {w}" for w in warnings] if len(filters or ()) > 1 else list(warnings)


def other_filters(plan, surface, gm, m, Ts, todo, views, emission, shape, unknowns_per_element: float
                  ) -> tuple[dict, list[str]]:
    """Each filter after the first: ``({name: (inputs, per pose, joint, ROI meter)}, its warnings)``,
    one T per pose for every filter (``gm``, ``Ts``: the first filter's unknowns and element T)."""
    others, warnings = {}, []
    refine = plan.transfer.subject.refine_faces
    for name in plan.filters[1:]:
        inp = from_capture(plan.images, surface.n_elements, name)
        t = plan.transmission(name)
        if inp.truth is not None and t != 1.0:
            inp.truth = inp.truth / t  # the light before the filter, as the results
        noise = noise_of(plan, inp)  # its own exposure
        stray = [light_outside(Ts[k], inp.images[k], inp.valid[k], noise, f"{pt.pose.label} (filter {name})", surface)
                 for k, (_, pt) in enumerate(todo)]
        meter = RoiMeter(plan.rois, plan.roi_mesh, surface, plan.rate_exposure_s(inp.exposure_s, inp.exposure_recorded))
        pp, joint = solve_poses(gm, inp, m, noise, stray, todo, shape, plan.joint, meter, t, f" (filter {name})")
        pp, joint = leave_out_edge_on(emission, views, todo, pp, joint)  # the same elements as the first filter's
        pp, joint, *_ = emission_checks(emission, views, todo, pp, joint, inp.images, inp.valid, noise)  # grazing views
        pp, joint, _ = checked_solves(pp, joint, inp, noise, Ts, unknowns_per_element, refine, todo)
        others[name] = (inp, pp, joint, meter)
        warnings += named(plan.filters, name, dark_poses(inp, todo, noise, Ts) + solve_warnings(pp, joint, todo))
    return others, warnings
