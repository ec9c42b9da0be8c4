"""What the escaping photons say about the surface: the face (of a triangle mesh of the
analytic body) each one left through, and the angular distribution of the light.

The mesh approximates the analytic body (a box exactly, a cylinder by an inscribed
prism). A photon's exit point is carried onto the mesh along a ray from inside the body (convex:
one crossing): from the centre for a box (whose mesh it lies on already), radially from
the axis for a cylinder's side (keeping its position along the axis), along the axis for
a cap; the triangle met is its face. Embree finds it.
"""

from __future__ import annotations

import numpy as np

from ..optics.raycast import OcclusionScene
from .transport import BOX, Shape


def faces_of_exits(shape: Shape, vertices_mm: np.ndarray, faces: np.ndarray, position_mm: np.ndarray,
                   *, scene: OcclusionScene | None = None) -> np.ndarray:
    """Index of the mesh face (vertices in the body's own frame) each exit point (n, 3)
    maps to; -1 where none is met (not expected on a closed mesh of the body)."""
    p = np.asarray(position_mm, float)
    scene = scene or OcclusionScene(vertices_mm, faces)
    if shape.kind == BOX:
        origin = np.zeros_like(p)
        d = p - origin
    else:
        # the side radially from the axis (keeps the position along it); a cap along the axis
        # from a point pulled halfway to the axis (inside the inscribed prism for any n >= 3)
        hx, r = shape.half_mm[0], shape.half_mm[1]
        rho = np.hypot(p[:, 1], p[:, 2])
        side = (hx - np.abs(p[:, 0])) >= (r - rho)
        origin = np.where(side[:, None], p * [1.0, 0.0, 0.0], p * [0.0, 0.49, 0.49])
        d = np.where(side[:, None], p - origin, np.sign(p[:, :1]) * [1.0, 0.0, 0.0])
    d = d / np.linalg.norm(d, axis=1)[:, None]
    _, face = scene.first_hit_face(origin, d)
    return face


def power_per_face(face_of_photon: np.ndarray, weight: np.ndarray, n_faces: int) -> np.ndarray:
    """Σ photon weights per face (photons)."""
    ok = face_of_photon >= 0
    return np.bincount(face_of_photon[ok], weights=weight[ok], minlength=n_faces)


ANGLE_EDGES_DEG = np.arange(0.0, 90.01, 2.5)


def exit_angle_histogram(normal: np.ndarray, direction: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Photons per bin of the angle between the outward normal and the direction in air
    (degrees, bins :data:`ANGLE_EDGES_DEG`)."""
    cos = np.clip(np.einsum("ij,ij->i", normal, direction), 0.0, 1.0)
    return np.histogram(np.degrees(np.arccos(cos)), bins=ANGLE_EDGES_DEG, weights=weight)[0]


def radiance_profile(histogram: np.ndarray, edges_deg: np.ndarray = ANGLE_EDGES_DEG,
                     fit_below_deg: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """Radiance relative to its value along the normal, L(θ)/L(0), from an exit-angle
    histogram: photons per bin / (solid angle × cos θ), i.e. per Δ(sin²θ); L(0) from a
    quadratic in (1 − cos θ) fitted to the bins below ``fit_below_deg``, each weighted by its
    Poisson variance (the bins near the normal hold few photons). Returns bin-centre
    angles (deg) and the profile."""
    e = np.radians(edges_deg)
    width = np.diff(np.sin(e) ** 2)
    per_proj_solid_angle = histogram / width  # dΩ cosθ = π d(sin²θ)
    sigma = np.sqrt(np.maximum(histogram, 1.0)) / width
    mid = np.degrees(np.arcsin(np.sqrt((np.sin(e[1:]) ** 2 + np.sin(e[:-1]) ** 2) / 2)))
    sel = mid < fit_below_deg
    coef = np.polyfit(1 - np.cos(np.radians(mid[sel])), per_proj_solid_angle[sel], 2, w=1 / sigma[sel])
    return mid, per_proj_solid_angle / coef[-1]


def redraw_directions(normal: np.ndarray, weight_table: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Directions in air drawn afresh about each outward normal (n, 3) from an emission profile
    given by its ray-weight table ``pi p(mu)`` on mu = k/(len-1) (:class:`fluxcli.optics.emission.
    Profile`.table; empty for Lambertian): the exit cosine has density ``2 w(mu) mu`` on [0, 1]
    (inverse CDF of the table's linear interpolant, by the trapezoid rule), the azimuth is uniform.
    The issue-21 control: the same exit points and weights with the angular law the model assumes."""
    normal = np.asarray(normal, float)
    table = np.asarray(weight_table, float)
    if table.size == 0:
        table = np.ones(2)
    mu = np.linspace(0.0, 1.0, table.size)
    if table.size < 1025:  # the density 2 w mu is quadratic per interval: a fine grid for the trapezoid CDF
        fine = np.linspace(0.0, 1.0, 4097)
        table, mu = np.interp(fine, mu, table), fine
    dens = 2.0 * table * mu
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(mu))])
    cdf /= cdf[-1]
    c = np.interp(rng.random(len(normal)), cdf, mu)
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    phi = rng.random(len(normal)) * 2.0 * np.pi
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(normal, t1)
    return c[:, None] * normal + s[:, None] * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
