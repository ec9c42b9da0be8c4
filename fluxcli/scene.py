"""From a validated config to the geometry the science packages take: camera, mirror
views, the subject placed at each pose, and the occluders.

Placement: a phantom rests on the stage top (``system.stage.top_z_mm + h``, or ``z = h``
without a stage), centred over the stage; a mesh (file or artefact) stays where its file
puts it and is raised by h.  A rotation turns the subject about its own axis (the
phantom's axis, or ``subject.rotation_axis``; for a mesh by default the x-direction line
through its bounding-box centre) before it is raised.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import config as C
from .errors import UserError
from .optics.camera import Aperture, PlaneMirror, ThinLensCamera
from .optics.emission import Profile
from .optics.transfer import View, views_for
from .surface import phantoms
from .surface.geometry import rotation_matrix as _rotation
from .surface.mesh import Surface, box, read_mesh_checked, rectangle, validated


@dataclass(frozen=True)
class Pose:
    height_mm: float
    rotation_deg: float

    @property
    def label(self) -> str:
        return f"h={self.height_mm:+g}mm rot={self.rotation_deg:g}deg"


@dataclass(frozen=True)
class PlacedScene:
    pose: Pose
    surface: Surface
    occluders: list[Surface]
    emission: Profile | None = None  # how the surface emits (None: Lambertian); part of T's cache key


def camera_from_config(cam: C.Camera) -> ThinLensCamera:
    return ThinLensCamera.from_pose(
        lens_center_mm=cam.pose.lens_center_mm, look=cam.pose.look, up=cam.pose.up,
        focal_length_mm=cam.lens.focal_length_mm, aperture_radius_mm=cam.lens.aperture_radius_mm,
        focus_distance_mm=cam.lens.focus_distance_mm, nx=cam.pixels[0], ny=cam.pixels[1],
        pixel_pitch_mm=cam.pixel_pitch_mm,
        apertures=tuple(Aperture(a.distance_mm, a.diameter_mm / 2) for a in cam.apertures),
    )


def mirror_names(system: C.System) -> list[str]:
    return [m.name or f"mirror{k}" for k, m in enumerate(system.mirrors)]


def plane_mirrors(system: C.System) -> list[PlaneMirror]:
    return [PlaneMirror.from_axis(m.center_mm, m.normal, m.axis, m.size_mm) for m in system.mirrors]


def views_from_config(system: C.System) -> list[View]:
    cam = camera_from_config(system.camera)
    mirrors = [(name, pm, m.reflectance * m.scale)
               for name, pm, m in zip(mirror_names(system), plane_mirrors(system), system.mirrors)]
    views = views_for(cam, mirrors)
    for v in views[1:]:
        if np.dot(cam.center_mm - v.mirror.center_mm, v.mirror.normal) <= 0:
            raise UserError(f"system.mirrors: mirror {v.name!r} faces away from the camera "
                            "(its normal must point to the side the lens is on).")
    _no_mirror_twice(mirror_names(system), plane_mirrors(system))
    return views


def _no_mirror_twice(names: list[str], mirrors: list[PlaneMirror]) -> None:
    """Two mirrors in one plane whose rectangles overlap are one piece of glass listed twice: each
    would add its view of the same light (the demo's mirror listed twice was simulated and
    reconstructed from two views of it, self-consistently, without a word)."""
    for i in range(len(mirrors)):
        for j in range(i + 1, len(mirrors)):
            a, b = mirrors[i], mirrors[j]
            if abs(float(a.normal @ b.normal)) < 1 - 1e-9 or abs(float((b.center_mm - a.center_mm) @ a.normal)) > 1e-6:
                continue
            # the rectangles in a's plane: overlapping unless an axis of either separates them (2-D SAT)
            corners = [m.center_mm + su * m.half_size_mm[0] * m.axis_u + sv * m.half_size_mm[1] * m.axis_v
                       for m in (a, b) for su in (-1, 1) for sv in (-1, 1)]
            ca, cb = np.array(corners[:4]), np.array(corners[4:])
            if all(max(ca @ ax) > min(cb @ ax) + 1e-9 and max(cb @ ax) > min(ca @ ax) + 1e-9
                   for ax in (a.axis_u, a.axis_v, b.axis_u, b.axis_v)):
                raise UserError(f"system.mirrors: mirrors {names[i]!r} and {names[j]!r} lie in one plane and overlap: "
                                "one mirror listed twice? Each mirror adds a view of the subject, so the same glass "
                                "twice would count its light twice.")


def mirror_cutting(placed: Surface, system: C.System) -> str | None:
    """The name of a mirror whose rectangle the placed surface crosses (vertices on both sides of
    its plane within it), or None. A mirror through the subject is a typing slip in center_mm
    or size_mm, or a stage raised into the mirror; it was simulated and reconstructed as given."""
    V = placed.vertices_mm
    span = float(np.ptp(V, axis=0).max()) if len(V) else 0.0
    for name, m in zip(mirror_names(system), plane_mirrors(system)):
        r = V - m.center_mm
        inside = (np.abs(r @ m.axis_u) <= m.half_size_mm[0]) & (np.abs(r @ m.axis_v) <= m.half_size_mm[1])
        d = (r @ m.normal)[inside]
        tol = 1e-6 * max(span, 1.0)
        if d.size and d.min() < -tol and d.max() > tol:
            return name
    return None


def stage_cutting(placed: Surface, stage: C.Stage | None, top_z_mm: float) -> float:
    """How deep (mm) the placed surface reaches into the stage below its top, within its footprint,
    where it also lies above the top (the stage's top plane cuts through the subject); 0 when it
    does not. A mesh stays where its file puts it, so a mesh centred on the origin sinks half into
    a stage at z = 0: its lower half is simulated and reconstructed hidden in the stage. A scanned
    surface's rim may lie a little under the top; ``STAGE_SLACK`` of the subject's height (at
    least 0.5 mm) is allowed."""
    if stage is None or not len(placed.vertices_mm):
        return 0.0
    V = placed.vertices_mm
    cx, cy = stage.center_xy_mm
    over = (np.abs(V[:, 0] - cx) <= stage.size_mm[0] / 2) & (np.abs(V[:, 1] - cy) <= stage.size_mm[1] / 2)
    z = V[over, 2]
    slack = max(0.5, STAGE_SLACK * float(np.ptp(V[:, 2])))
    if not z.size or z.max() <= top_z_mm or z.min() >= top_z_mm - slack:
        return 0.0
    return float(top_z_mm - z.min())


STAGE_SLACK = 0.02


def poses_from_config(subject: C.Subject) -> list[Pose]:
    p = subject.poses or C.Poses()
    return [Pose(float(h), float(r)) for h in p.heights_mm for r in p.rotations_deg]


class SubjectPlacer:
    """Builds the subject surface once and places it at any pose."""

    def __init__(self, subject: C.Subject, stage: C.Stage | None, emission: Profile,
                 resolve: Callable[[Path], Path] = Path):
        """``subject``: the config's subject section; ``stage``: the rig's stage (what a phantom rests
        on), or None; ``emission``: the surface's emission profile; ``resolve``: turns a path the
        config gives into the file it means (beside the config)."""
        s = subject.surface
        self.surface_config = s  # subject.surface as given (what a Monte Carlo run names when it refuses a mesh)
        self.stage = stage
        self.rests_on_stage = isinstance(s, (C.CylinderPhantom, C.BoxPhantom, C.RingPhantom, C.SpherePhantom))
        self.notes: list[str] = []  # what a mesh file yielded and what was repaired in it
        self.warnings: list[str] = []  # what placing it found (a stage through the subject)
        self.emission = emission  # Lambertian when subject.emission is absent
        body = None  # a round phantom's own curved surface, which split faces follow
        if isinstance(s, C.CylinderPhantom):
            surf, point, axis = phantoms.cylinder(radius_mm=s.radius_mm, length_mm=s.length_mm, n_angular=s.n_angular,
                                                  n_axial=s.n_axial, cap_elements=s.cap_elements)
            body = phantoms.RoundBody(s.radius_mm, axis=0)
        elif isinstance(s, C.BoxPhantom):
            surf, point, axis = phantoms.box(size_mm=s.size_mm, element_mm=s.element_mm)
        elif isinstance(s, C.RingPhantom):
            surf, point, axis = phantoms.ring(radius_mm=s.radius_mm, thickness_mm=s.thickness_mm, n_elements=s.n_elements,
                                              strips_per_element=s.strips_per_element)
            body = phantoms.RoundBody(s.radius_mm, axis=1)
        elif isinstance(s, C.SpherePhantom):
            surf, point, axis = phantoms.sphere(radius_mm=s.radius_mm, n_latitude=s.n_latitude, n_longitude=s.n_longitude)
            body = phantoms.RoundBody(s.radius_mm)
        elif isinstance(s, C.PatchPhantom):
            surf, point, axis = phantoms.patch(size_mm=s.size_mm, n=s.n, center_mm=s.center_mm, normal=s.normal)
        elif isinstance(s, C.MeshSurface):
            path = resolve(s.mesh)
            try:
                surf, self.notes = read_mesh_checked(path, scale_to_mm=s.scale_to_mm)
            except ValueError as e:
                raise UserError(f"subject.surface.mesh: {e}.") from None
            lo, hi = surf.bounds_mm()
            point, axis = (lo + hi) / 2, np.array([1.0, 0, 0])
        else:  # surface artefact from capture-surface
            from .artefacts import surface as AS

            path = resolve(s.artefact)
            if not path.is_file():
                raise UserError(f"subject.surface.artefact: {path} does not exist; it is made by "
                                f"'fluxmap capture-surface' (capture.surface), run that first.")
            try:
                surf = AS.read(path, decode=False).surface
            except UserError as e:
                raise UserError(f"subject.surface.artefact: {e}") from None
            try:
                surf, self.notes = validated(surf.vertices_mm, surf.faces, surf.element_of_face, surf.n_elements,
                                             name=str(path), element_ids=surf.element_ids)
            except ValueError as e:
                raise UserError(f"subject.surface.artefact: {e}.") from None
            lo, hi = surf.bounds_mm()
            point, axis = (lo + hi) / 2, np.array([1.0, 0, 0])
        if surf.n_elements == 0:
            raise UserError("subject.surface: the surface has no elements.")
        n_faces = len(surf.faces) * 4 ** subject.refine_faces
        if n_faces > C.MAX_PHANTOM_PIECES:
            raise UserError(f"subject.refine_faces: {subject.refine_faces} splits the surface's {len(surf.faces)} faces "
                            f"into {n_faces:.3g}; at most {C.MAX_PHANTOM_PIECES:.0e} (no camera resolves more, and "
                            "building them would exhaust the memory). Lower subject.refine_faces.")
        surf = surf.subdivided(subject.refine_faces, body)  # finer faces (on a round phantom's body), the same elements
        self.own_surface = surf  # in the generator's own frame (what a Monte Carlo truth is computed in)
        self.rest_shift_mm = np.zeros(3)
        if self.rests_on_stage:
            surf, point = self._rest(surf, point, 0.0)
            self.rest_shift_mm = surf.vertices_mm[0] - self.own_surface.vertices_mm[0]
        ra = subject.rotation_axis
        if ra is not None:
            axis = np.asarray(ra.direction, float)
            if ra.point_mm is not None:
                point = np.asarray(ra.point_mm, float)
        self.surface, self.axis_point, self.axis = surf, np.asarray(point, float), axis / np.linalg.norm(axis)

    def _stage_top(self, h: float) -> float:
        return (self.stage.top_z_mm if self.stage else 0.0) + h

    def _rest(self, surf: Surface, point: np.ndarray, h: float) -> tuple[Surface, np.ndarray]:
        cxy = np.array(self.stage.center_xy_mm) if self.stage else np.zeros(2)
        lo, hi = surf.bounds_mm()
        shift = np.array([cxy[0] - (lo[0] + hi[0]) / 2, cxy[1] - (lo[1] + hi[1]) / 2, self._stage_top(h) - lo[2]])
        return surf.transformed(np.eye(3), shift), point + shift

    def placement(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """(R, t): the pose places a point x of ``self.surface`` at R x + t."""
        R = _rotation(self.axis, pose.rotation_deg)
        t = self.axis_point - R @ self.axis_point + np.array([0, 0, pose.height_mm])
        if self.rests_on_stage:  # a faceted phantom turned by an odd angle must still sit on the stage
            lo = (self.surface.vertices_mm @ R.T + t)[:, 2].min()
            t = t + np.array([0, 0, self._stage_top(pose.height_mm) - lo])
        return R, t

    def place(self, pose: Pose) -> Surface:
        R = _rotation(self.axis, pose.rotation_deg)
        t = self.axis_point - R @ self.axis_point + np.array([0, 0, pose.height_mm])
        placed = self.surface.transformed(R, t)
        if self.rests_on_stage:  # a faceted phantom turned by an odd angle must still sit on the stage
            lo = placed.bounds_mm()[0]
            placed = placed.transformed(np.eye(3), np.array([0, 0, self._stage_top(pose.height_mm) - lo[2]]))
        return placed

    def occluders(self, pose: Pose, system: C.System) -> list[Surface]:
        occ = []
        if self.stage is not None:
            st = self.stage
            top = self._stage_top(pose.height_mm)
            cx, cy = st.center_xy_mm
            occ.append(box([cx - st.size_mm[0] / 2, cy - st.size_mm[1] / 2, top - st.thickness_mm],
                           [cx + st.size_mm[0] / 2, cy + st.size_mm[1] / 2, top]))
        for m in plane_mirrors(system):
            occ.append(rectangle(m.center_mm, m.axis_u, m.axis_v, (2 * m.half_size_mm[0], 2 * m.half_size_mm[1])))
        return occ

    def scene(self, pose: Pose, system: C.System) -> PlacedScene:
        placed = self.place(pose)
        cut = mirror_cutting(placed, system)
        if cut is not None:
            raise UserError(f"system.mirrors: mirror {cut!r} passes through the subject at pose {pose.label} (the "
                            "surface lies on both sides of its plane within its rectangle): check the mirror's "
                            "center_mm and size_mm, and subject.poses (the stage raises the subject).")
        if not self.rests_on_stage and not self.warnings and (
                deep := stage_cutting(placed, self.stage, self._stage_top(pose.height_mm))):
            lo = self.surface.bounds_mm()[0][2]
            self.warnings.append(
                f"subject.surface: at pose {pose.label} the subject reaches {deep:.3g} mm into the stage (below its top "
                f"at z = {self._stage_top(pose.height_mm):g} mm, within system.stage.size_mm): what lies inside the "
                f"stage is hidden from every view, and is simulated and reconstructed so (unobserved). A mesh stays "
                f"where its file puts it (its lowest point at rest is at z = {lo:.4g} mm; it is not set on the stage): "
                "if the subject rests on the stage, move it up in the file or lower system.stage.top_z_mm.")
        return PlacedScene(pose, placed, self.occluders(pose, system), self.emission)
