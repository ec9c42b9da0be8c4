"""capture-surface's last step: from the pattern frames of capture.h5 to ``surface.h5`` (decode,
triangulate over every view and projector, merge, mesh; :mod:`fluxcli.structured` does the maths)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..errors import UserError
from ._capture_plan import CapturePlan, patterns
from ._capture_scene import camera_at_binning
from ._radiometric import assumed_qe_warning
from .context import RunContext


def make_surface(plan: CapturePlan, ctx: RunContext, scene, capture_path: Path) -> Path:
    """Decode the pattern frames of ``capture_path``, triangulate, mesh, write ``surface.h5``."""
    from ..artefacts.capture import read_patterns
    from ..hardware.projector import projector_model
    from ..imaging.noise import pattern_photons
    from ..artefacts.surface import write_surface_artefact
    from ..structured.scan import decode_by_view
    from .plans import emccd_model
    from ..scene import mirror_names, plane_mirrors
    from ..structured.mesh import capture_metrics, distances_to_surface
    from ..structured.scan import merge_points, points_from_frames, surface_from_points

    sf, system, rig = plan.capture.surface, plan.system, plan.rig
    out = plan.surface_output
    digest = A.inputs_digest(capture=A.file_sha256(capture_path), surface=sf.model_dump(mode="json"),
                             system=system.model_dump(mode="json"),
                             projectors={k: v.model_dump(mode="json") for k, v in rig.projectors.items()})
    if not ctx.force and A.is_up_to_date(out, "surface", digest):
        ctx.say(f"capture-surface: {out} is up to date")
        return out
    pc = read_patterns(capture_path)
    camera = camera_at_binning(system.camera, (rig.camera or C.RigCamera()).binning // pc.binning)
    mirrors = plane_mirrors(system)
    views = ["direct"] + mirror_names(system)
    photons = pattern_photons(pc, emccd_model(system.camera.sensor, pc.exposure_s))
    warning = assumed_qe_warning(system, "capture-surface", real_counts=scene is None)
    if warning:
        ctx.say(warning)
    scans = []
    with ctx.progress("decode", len(pc.projectors)) as tick:
        for name in pc.projectors:
            ps = patterns(sf, rig.projectors[name])
            scan = points_from_frames(photons[name], ps, camera, mirrors, projector_model(rig.projectors[name]),
                                      min_contrast=sf.min_contrast_photons,
                                      min_modulation_fraction=sf.min_modulation_fraction)
            scans.append(scan)
            tick()
    decode = decode_by_view(scans, list(pc.projectors), views, camera, mirrors)
    h = pc.height_mm
    floor = (system.stage.top_z_mm + h) if system.stage is not None else None
    merged = merge_points(scans, floor_z_mm=-np.inf if floor is None else floor)
    if len(merged.points_mm) < 50:
        raise UserError(f"capture-surface: only {len(merged.points_mm)} points were decoded from the pattern frames "
                        f"of {capture_path}; is the subject lit (rig.projectors) and the shadow mask "
                        f"(capture.surface.min_contrast_photons = {sf.min_contrast_photons:g}) right?")
    ctx.say(f"capture-surface: {len(merged.points_mm)} points "
            f"({', '.join(f'{v} {int((merged.view == j).sum())}' for j, v in enumerate(views))}); meshing ...")
    mesh = surface_from_points(merged, floor_z_mm=floor, element_size_mm=sf.mesh.element_size_mm,
                               face_size_mm=sf.mesh.face_size_mm, voxel_mm=sf.mesh.voxel_mm,
                               centre_spacing_mm=sf.mesh.centre_spacing_mm)
    distance = truth = metrics = None
    if scene is not None:  # the simulated rig knows the truth
        truth = scene.true_surface_at(h)
        distance = distances_to_surface(merged.points_mm, truth)
        metrics = capture_metrics(merged.points_mm, distance, mesh, truth)
        truth = truth.transformed(np.eye(3), np.array([0.0, 0.0, -h]))
        ctx.say("capture-surface: points within 0.1 / 0.2 / 0.4 mm of the true surface: "
                + " / ".join(f"{np.mean(distance < t):.1%}" for t in (0.1, 0.2, 0.4)))
    # at rest: as with the stage at height 0 (poses raise it by their height)
    shift = np.array([0.0, 0.0, -h])
    mesh = mesh.transformed(np.eye(3), shift)
    merged.points_mm = merged.points_mm + shift
    write_surface_artefact(out, mesh, points=merged, decode=decode, distance_to_truth_mm=distance, truth=truth, metrics=metrics,
                           config_sha256=plan.config_sha256, inputs={"capture": A.file_sha256(capture_path)},
                           provenance=plan.surface_provenance, attrs={"inputs_digest": digest, "capture_height_mm": h})
    ctx.say(f"capture-surface: {out}: {len(mesh.faces)} faces, {mesh.n_elements} elements, "
            f"area {mesh.face_areas_mm2.sum():.0f} mm^2")
    return out
