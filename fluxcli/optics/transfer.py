"""The free-space transfer matrix T (pixels x elements, dimensionless).

``T[i, j]`` is the fraction of the power emitted (uniform over the element, with the angular
profile of :mod:`fluxcli.optics.emission`, Lambertian by default) by surface element j that
lands in pixel i, so images are ``a = T b`` with b in photons.  A non-Lambertian profile
multiplies each ray's weight below by ``pi p(theta_s)``.
Two estimators of the same integral (DESIGN.md section 3):

``lens`` (default)
    surface samples x lens-disk samples; each pair is one ray r -> r_l whose line meets
    the front focal plane at r_vd, which fixes the pixel.  Weight
    ``cos(theta_s) cos(theta_l) / (pi |r_l - r|^2) dA_l dS``.  The number of lens samples
    per surface point follows the blur-disk area in pixels.
``pairwise`` (the paper's)
    surface samples x sub-pixel centres on the focal plane; weight
    ``cos(theta_s) cos(theta_d) / (pi |r_vd - r|^2) dA_vd dS``, counted when the line
    crosses the lens disk (alpha) inside every extra aperture (beta).

Both share one pair filter: beta, the mirror window, and Embree visibility of the real
segments (surface -> lens, or surface -> mirror -> lens).

Fewer rays for the same accuracy (``lens``): faces whose every segment is provably clear
are not cast (:mod:`fluxcli.optics.visibility`, T unchanged to the bit); each surface sample
turns its lens pattern, so that an element's lens error averages over its samples; and with
``LensSampling.target_column_error`` an element is cast in doubling rounds until its column's
error estimate meets the target.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import scipy.sparse as sp

from ..surface.mesh import Surface, merge
from . import visibility
from .camera import PlaneMirror, ThinLensCamera, sunflower_disk
from .emission import Profile
from .raycast import OcclusionScene

ALGORITHM_VERSION = "transfer-3"  # bump whenever the numbers an estimator gives change


@dataclass(frozen=True)
class View:
    """One way light reaches the detector: directly, or via one plane mirror."""

    name: str
    camera: ThinLensCamera  # the real camera, or its virtual copy in ``mirror``
    mirror: PlaneMirror | None = None
    weight: float = 1.0  # reflectance x per-view scale


@dataclass(frozen=True)
class LensSampling:
    surface_samples_per_pixel: float = 2.0
    min_surface_subdivisions: int = 1
    max_surface_subdivisions: int = 48
    lens_samples_min: int = 32
    lens_samples_max: int = 2048
    lens_samples_per_blur_pixel: float = 4.0
    target_column_error: float = 0.0  # adaptive rounds until the column's estimate <= this x its sum (0: off)


@dataclass(frozen=True)
class PairwiseSampling:
    surface_subdivisions: int = 6
    pixel_subdivisions: int = 3


@dataclass
class TransferResult:
    """T per view (unweighted) and combined (sum of view weight x view T)."""

    views: list[View]
    T_per_view: list[sp.csr_matrix]
    T: sp.csr_matrix
    stats: dict[str, dict[str, float]] = field(default_factory=dict)
    column_error_per_view: list[np.ndarray] = field(default_factory=list)  # per view, L1 error estimate per column
    column_error: np.ndarray | None = None  # of T: sum over views of weight x view's estimate
    # the tangential-flux term (emission profiles with one): (n_pixels, 2 n_elements), column 2j + a
    # the component along the face's in-plane unit vector a (emission.face_frames) of the sum over
    # rays of weight x g x direction (mm); for an element of several faces each in its own face's
    # frame (meaningful for one face per element, as the vertex basis's fine T); sum of weight x view's
    T_tangent: sp.csr_matrix | None = None
    T_tangent_per_view: list = field(default_factory=list)


# ------------------------------------------------------------------ surface sampling
def subtriangle_barycentrics(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric centroids of the n^2 congruent sub-triangles of a triangle, (n^2, 3),
    and their orientation (+1 for the n(n+1)/2 upright ones, -1 for the inverted ones,
    which are the upright shape turned 180 degrees about the centroid)."""
    pts, sign = [], []
    for i in range(n):
        for j in range(n - i):
            pts.append((i + 1 / 3, j + 1 / 3))
            sign.append(1.0)
            if i + j <= n - 2:
                pts.append((i + 2 / 3, j + 2 / 3))
                sign.append(-1.0)
    ab = np.array(pts) / n
    return np.column_stack([1 - ab.sum(axis=1), ab]), np.array(sign)


def sample_faces(surface: Surface, face_ids: np.ndarray, n_sub: np.ndarray, return_faces: bool = False):
    """Sub-triangle centroid samples of the given faces.

    Returns points (S, 3) mm, normals (S, 3), element index (S,), the fraction of the
    element's area each sample stands for (S,), and the two edge vectors of each sample's
    sub-triangle (S, 2, 3), signed so that ``p + (a - 1/3) e0 + (b - 1/3) e1`` with
    ``a, b >= 0, a + b <= 1`` covers exactly that sub-triangle; with ``return_faces`` also
    the face of each sample (S,).
    """
    tri = surface.face_vertices_mm
    normals = surface.face_normals
    areas = surface.face_areas_mm2
    el_area = surface.element_areas_mm2
    out_p, out_n, out_e, out_w, out_edges, out_f = [], [], [], [], [], []
    for n in np.unique(n_sub):
        f = face_ids[n_sub == n]
        out_f.append(np.repeat(f, n * n))
        bary, sign = subtriangle_barycentrics(int(n))
        p = np.einsum("kc,fcd->fkd", bary, tri[f]).reshape(-1, 3)
        per_face = len(bary)  # samples per face
        e = np.repeat(surface.element_of_face[f], per_face)
        edges = np.stack([tri[f, 1] - tri[f, 0], tri[f, 2] - tri[f, 0]], axis=1) / n  # (F, 2, 3)
        out_p.append(p)
        out_n.append(np.repeat(normals[f], per_face, axis=0))
        out_e.append(e)
        out_w.append(np.repeat(areas[f] / (n * n), per_face) / el_area[e])
        out_edges.append((edges[:, None] * sign[None, :, None, None]).reshape(-1, 2, 3))
    if not out_p:
        z = np.zeros((0, 3))
        out = z, z, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2, 3))
        return (*out, np.zeros(0, np.int64)) if return_faces else out
    out = (np.concatenate(out_p), np.concatenate(out_n), np.concatenate(out_e), np.concatenate(out_w),
           np.concatenate(out_edges))
    return (*out, np.concatenate(out_f)) if return_faces else out


def square_points(n: int) -> np.ndarray:
    """``n`` well-spread points of the unit square (Roberts' R2 sequence), shape (n, 2)."""
    g = 1.32471795724474602596
    i = np.arange(n) + 0.5
    return np.column_stack([(i / g) % 1.0, (i / g**2) % 1.0])


def triangle_jitter(n: int) -> np.ndarray:
    """``n`` well-spread points of the unit triangle (a, b >= 0, a + b <= 1), centred on its
    centroid: offsets (n, 2) with mean ~0.  Roberts' R2 sequence folded into the triangle."""
    a, b = square_points(n).T
    fold = a + b > 1
    a, b = np.where(fold, 1 - a, a), np.where(fold, 1 - b, b)
    # decorrelate from the lens spiral, which is ordered by radius
    order = (np.arange(n) * 7919) % n if n % 7919 else np.arange(n)
    return np.column_stack([a, b])[order] - 1 / 3


def lens_pattern(n: int, n_cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lens and surface points of a sample with ``n`` lens samples, and of its adaptive
    rounds up to ``n_cap``: lens points on the unit disk, in the unit square and surface
    offsets in the unit triangle, each (N, 2) with N = n 2^p <= max(n, n_cap).

    Points ``[0, n)`` are round 0 (Vogel's spiral, the R2 square and the folded R2 jitter of
    n points); round p >= 1 adds points ``[n 2^(p-1), n 2^p)``: a spiral of n 2^(p-1) points
    turned by an irrational angle and its own jitter, so that every round is by itself an
    evenly spread set and the rounds so far, weighted equally per ray, are one estimate.
    The square points are one R2 sequence (any prefix is evenly spread)."""
    total = n
    while 2 * total <= n_cap:
        total *= 2
    disks, jits = [sunflower_disk(n)], [triangle_jitter(n)]
    m, rnd = n, 1
    while sum(len(d) for d in disks) < total:
        turn = 2 * np.pi * ((rnd * 0.7548776662466927) % 1.0)
        c, s_ = np.cos(turn), np.sin(turn)
        d = sunflower_disk(m)
        disks.append(d @ np.array([[c, s_], [-s_, c]]))
        j = triangle_jitter(m)
        jits.append(j[::-1] if rnd % 2 else j)
        m, rnd = sum(len(d) for d in disks), rnd + 1
    return np.concatenate(disks), square_points(total), np.concatenate(jits)


def _candidate_faces(surface: Surface, view: View) -> np.ndarray:
    """Emitting faces that can possibly send light into this view's lens."""
    cam = view.camera
    tri = surface.face_vertices_mm
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(axis=1)
    ok = surface.element_of_face >= 0
    # some lens point in front of the face: n.(L - p) > 0 for some L, p on the face
    ok &= np.einsum("ij,ij->i", surface.face_normals, cam.center_mm - cen) > -(cam.aperture_radius_mm + rad)
    ok &= cam.axial(cen) + rad > 0
    if view.mirror is not None:
        ok &= (cen - view.mirror.center_mm) @ view.mirror.normal + rad > 0
    return np.flatnonzero(ok)


# ------------------------------------------------------------------ the shared pair filter
class _PairFilter:
    def __init__(self, view: View, scene: OcclusionScene, ray_offset_mm: float):
        self.view, self.scene, self.eps = view, scene, ray_offset_mm
        self.rays_cast = 0

    def __call__(self, P, N, L, pix, w, elem, axial_p):
        """Keep the visible pairs; returns (pix, elem, w); their indices are left in ``self.kept``."""
        view, cam, eps = self.view, self.view.camera, self.eps
        keep = (w > 0) & (pix >= 0)
        keep[keep] &= cam.passes_apertures(P[keep], L[keep], axial_p[keep])
        idx = np.flatnonzero(keep)
        P, N, L = P[idx], N[idx], L[idx]
        O = P + eps * N
        if view.mirror is None:
            d = L - O
            length = np.linalg.norm(d, axis=1)
            blocked = self.scene.blocked(O, d / length[:, None], length)
            self.rays_cast += len(idx)
        else:
            m = view.mirror
            d = L - O
            denom = d @ m.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((m.center_mm - O) @ m.normal) / denom
            M = O + t[:, None] * d
            good = (t > 0) & (t < 1) & m.contains(M)
            L_real = m.reflect_points(L)
            s1 = M - O
            l1 = np.linalg.norm(s1, axis=1)
            s2 = L_real - M
            l2 = np.linalg.norm(s2, axis=1)
            blocked = ~good
            g = np.flatnonzero(good)
            if len(g):
                u1 = s1[g] / l1[g, None]
                u2 = s2[g] / l2[g, None]
                b1 = self.scene.blocked(O[g], u1, l1[g] - eps)
                b2 = self.scene.blocked(M[g] + eps * u2, u2, l2[g] - eps)
                blocked[g] = b1 | b2
                self.rays_cast += 2 * len(g)
        vis = idx[~blocked]
        self.kept = vis
        return pix[vis], elem[vis], w[vis]


# ------------------------------------------------------------------ estimators
def _sampling_disks(cam: ThinLensCamera, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per surface point, the smallest disk in the lens plane that holds every line from the
    point through the lens and all extra apertures: the lens disk itself, or the shadow of
    an aperture (radius rho z / (z - a), centred where the line to its centre lands).

    Returns centre offsets from the lens centre (S, 3) and radii (S,) in mm.
    """
    centre = np.zeros_like(P)
    radius = np.full(len(P), cam.aperture_radius_mm)
    lateral = (P - cam.center_mm) - z[:, None] * cam.axis
    for ap in cam.apertures:
        in_front = z > ap.distance_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            r = ap.radius_mm * z / (z - ap.distance_mm)
        smaller = in_front & (r < radius)
        radius = np.where(smaller, r, radius)
        shift = -(ap.distance_mm / np.where(in_front, z - ap.distance_mm, 1.0))[:, None] * lateral
        centre = np.where(smaller[:, None], shift, centre)
    return centre, radius


def _lens_subdivisions(surface: Surface, faces: np.ndarray, cam, s: LensSampling) -> np.ndarray:
    """Sub-triangles per edge of each face: ``surface_samples_per_pixel`` per pixel footprint."""
    tri = surface.face_vertices_mm[faces]
    edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    z_face = np.maximum(cam.axial(tri.mean(axis=1)), 1e-6)
    footprint = cam.focal_pixel_mm * z_face / cam.focus_distance_mm  # pixel size seen at that depth
    return np.clip(np.ceil(edge / footprint * s.surface_samples_per_pixel),
                   s.min_surface_subdivisions, s.max_surface_subdivisions).astype(np.int64)


def surface_sample_count(surface: Surface, views: list[View], estimator: str = "lens",
                         lens_sampling: LensSampling | None = None,
                         pairwise_sampling: PairwiseSampling | None = None) -> int:
    """How many surface points :func:`build_transfer` holds in memory at once for its
    largest view (before lens sampling, which is batched): for sizing a job beforehand."""
    most = 0
    for view in views:
        faces = _candidate_faces(surface, view)
        if estimator == "lens":
            n = _lens_subdivisions(surface, faces, view.camera, lens_sampling or LensSampling())
        else:
            n = np.full(len(faces), (pairwise_sampling or PairwiseSampling()).surface_subdivisions)
        most = max(most, int(np.sum(n.astype(np.float64) ** 2)))
    return most


@dataclass
class _LensPlan:
    """Per surface sample (sorted by element) everything the compiled loop needs, and the
    chunks of whole elements it is cast in."""

    points_mm: np.ndarray  # (S, 3) the sample's point (a sub-triangle's centroid)
    normals: np.ndarray  # (S, 3) its face's unit normal
    edges_mm: np.ndarray  # (S, 2, 3) its sub-triangle's edges (each ray jitters its point within)
    ray_area_mm2: np.ndarray  # (S,) lens-plane area per lens sample x the sample's share of its element's area
    element: np.ndarray  # (S,) int64, non-decreasing
    box_lo_mm: np.ndarray  # (S, 2) lens-plane box (right, down) of the lens points whose rays reach the sensor
    box_hi_mm: np.ndarray  # (S, 2)
    disk_center_mm: np.ndarray  # (S, 2) the aperture disk seen from the sample, on the lens plane
    disk_radius_mm: np.ndarray  # (S,)
    use_box: np.ndarray  # (S,) bool: sample the box (smaller than the disk) rather than the disk
    n_lens: np.ndarray  # (S,) lens samples of the first round
    pat_off: np.ndarray  # (S,) where its lens pattern starts in the concatenated patterns
    disk_unit: np.ndarray
    square_unit: np.ndarray
    jitter: np.ndarray
    chunks: list[tuple[int, int]]  # sample ranges [s0, s1), each whole elements
    rays: int
    clear: np.ndarray  # (S,) uint8: which of the sample's segments are known clear (visibility.clear_faces)
    spin: np.ndarray  # (S, 4): per sample the turn (cos, sin) of its disk pattern and the shift of its square one
    margin_mm: float  # a mirror segment is known clear only this far (x2) in front of the mirror
    target: float  # adaptive rounds: the column error target (0: one round)
    n_cap: int  # adaptive rounds: lens samples per surface sample, at most
    emis: np.ndarray = field(default_factory=lambda: np.zeros(0))  # ray weights pi p on cos theta (empty: Lambertian)
    tang: np.ndarray = field(default_factory=lambda: np.zeros(0))  # tangential weights pi p g, mm (empty: off)
    tframe: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # per sample its face's frame


def _lens_plan(surface: Surface, view: View, s: LensSampling, rays_per_batch: int,
               tree: "visibility.LazyTree | None" = None, ray_offset_mm: float = 1e-3,
               turn_patterns: bool = True, emission: Profile | None = None) -> _LensPlan | None:
    """Surface samples, their lens-sampling regions and counts (vectorised over samples,
    O(samples) work); the per-ray work is :func:`fluxcli.optics.transfer_kernel.lens_columns`.
    With ``tree`` (the occluders), the faces whose every segment is clear are found
    (:func:`fluxcli.optics.visibility.clear_faces`) and their rays are not cast, when the view
    has enough rays per face to repay the test."""
    cam = view.camera
    faces = _candidate_faces(surface, view)
    if len(faces) == 0:
        return None
    n_sub = _lens_subdivisions(surface, faces, cam, s)
    points, normals, element, area_share, edges, face = sample_faces(surface, faces, n_sub, return_faces=True)
    depth = cam.axial(points)
    front = (depth > 0) & (np.einsum("ij,ij->i", normals, cam.center_mm - points) > -cam.aperture_radius_mm)
    points, normals, element, area_share, depth, edges, face = (
        points[front], normals[front], element[front], area_share[front], depth[front], edges[front], face[front])
    disk_world, disk_radius = _sampling_disks(cam, points, depth)
    # Clip the sampling to the lens points whose rays land on the sensor: the ray from the
    # surface point p (at depth z) through the lens point L meets the focal plane (depth u) at
    # X = (1 - u/z) L + (u/z) p (lateral), so the sensor's preimage on the lens plane is a
    # rectangle.  ``to_focus`` = u/z is where along lens -> p the focal plane lies; ``defocus``
    # = 1 - u/z scales the lens disk into the blur on the focal plane (0: in focus).  A line
    # sensor or a point near the image edge then needs only a sliver of the lens.  Jitter moves
    # p by up to one sub-triangle: pad for it.
    u, pf = cam.focus_distance_mm, cam.focal_pixel_mm
    to_focus = u / depth
    defocus = 1 - to_focus
    lateral = np.stack([(points - cam.center_mm) @ cam.right, (points - cam.center_mm) @ cam.down], axis=1)
    disk_center = np.stack([disk_world @ cam.right, disk_world @ cam.down], axis=1)  # lens plane
    half = np.array([cam.nx, cam.ny]) * pf / 2
    grain = np.linalg.norm(edges, axis=2).max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ends = (np.stack([-half, half])[:, None, :] - to_focus[None, :, None] * lateral[None]) / defocus[None, :, None]
        pad = (to_focus * grain / np.abs(defocus))[:, None]
        box_lo = np.maximum(np.min(ends, axis=0) - pad, disk_center - disk_radius[:, None])  # inf - inf where focused
        box_hi = np.minimum(np.max(ends, axis=0) + pad, disk_center + disk_radius[:, None])
    focused = ~np.isfinite(ends).all(axis=(0, 2))  # defocus 0: all rays meet at one focal point
    box_lo[focused] = (disk_center - disk_radius[:, None])[focused]
    box_hi[focused] = (disk_center + disk_radius[:, None])[focused]
    hits = np.flatnonzero(np.all(box_hi > box_lo, axis=1) | focused)
    # grouped by element (stable: the sampling order within an element is kept), so that each
    # element's column is finished in one piece; one gather per array
    keep = hits[np.argsort(element[hits], kind="stable")]
    (points, normals, element, area_share, depth, edges, face, box_lo, box_hi, disk_center, disk_radius,
     defocus) = (np.ascontiguousarray(x[keep]) for x in (points, normals, element, area_share, depth, edges, face,
                                                         box_lo, box_hi, disk_center, disk_radius, defocus))
    box_area = np.prod(box_hi - box_lo, axis=1)
    use_box = box_area < 0.6 * np.pi * disk_radius**2
    # the blur the sampled region paints, in pixels: sample its area at the requested density
    extent_px = np.where(use_box[:, None], (box_hi - box_lo), 2 * disk_radius[:, None]) * np.abs(defocus)[:, None] / pf
    painted = np.prod(np.maximum(extent_px, 1.0), axis=1)
    want = np.clip(np.ceil(s.lens_samples_per_blur_pixel * painted), s.lens_samples_min, s.lens_samples_max)
    # quantise to powers of two above the minimum, so that few patterns serve all samples
    level = np.ceil(np.log2(want / s.lens_samples_min)).astype(int)
    n_lens = np.minimum(s.lens_samples_min * 2**level, s.lens_samples_max).astype(np.int64)
    area = np.where(use_box, box_area, np.pi * disk_radius**2)
    ray_area = area / n_lens * area_share
    # one pattern per distinct count, with its adaptive rounds: lens disk, box and surface jitter
    counts = np.unique(n_lens)
    pats = [lens_pattern(int(n), s.lens_samples_max if s.target_column_error > 0 else int(n)) for n in counts]
    starts = np.concatenate([[0], np.cumsum([len(p[0]) for p in pats])]).astype(np.int64)
    pat_off = starts[np.searchsorted(counts, n_lens)]
    disk_unit, square_unit, jitter = ((np.concatenate([p[i] for p in pats]) if pats else np.zeros((0, 2)))
                                      for i in range(3))
    chunks = _element_chunks(element, n_lens, rays_per_batch)
    clear = np.zeros(len(points), np.uint8)
    margin = visibility.MARGIN_MM
    if tree is not None and len(points) and n_lens.sum() >= visibility.MIN_RAYS_PER_FACE * len(faces):
        used, at = np.unique(face, return_inverse=True)
        occ = tree.get()
        margin = occ.margin_mm
        flags = visibility.clear_faces(occ, surface.face_vertices_mm[used], surface.face_normals[used],
                                       cam.center_mm, cam.aperture_radius_mm, ray_offset_mm, view.mirror)
        clear = np.ascontiguousarray(flags[at])
    return _LensPlan(points, normals, edges, ray_area, element.astype(np.int64), box_lo, box_hi, disk_center,
                     disk_radius, use_box, n_lens, pat_off,
                     np.ascontiguousarray(disk_unit), np.ascontiguousarray(square_unit), np.ascontiguousarray(jitter),
                     chunks, int(n_lens.sum()), clear, _spins(element, turn_patterns),
                     margin, float(s.target_column_error),
                     int(s.lens_samples_max), _emission_table(emission), _tangent_table(emission),
                     _frames(surface, face, emission))


def _emission_table(emission: Profile | None) -> np.ndarray:
    """The kernel's ray-weight table: empty (Lambertian, weight 1) or pi p on the cos grid."""
    if emission is None or emission.is_lambertian:
        return np.zeros(0)
    return np.ascontiguousarray(emission.table, np.float64)


def _tangent_table(emission: Profile | None) -> np.ndarray:
    """The kernel's tangential-weight table: empty (no tangential term) or pi p g on the cos grid."""
    if emission is None or not emission.has_tangent:
        return np.zeros(0)
    return np.ascontiguousarray(emission.tangent, np.float64)


def _frames(surface: Surface, faces: np.ndarray, emission: Profile | None) -> np.ndarray:
    """Per sample the in-plane unit vectors of its face (S, 2, 3); (0, 2, 3) when the term is off."""
    if emission is None or not emission.has_tangent:
        return np.zeros((0, 2, 3))
    from .emission import face_frames

    return np.ascontiguousarray(face_frames(surface.face_vertices_mm[faces]))


def _tangent_csr(results: list, n_pix: int, n_el: int) -> sp.csr_matrix:
    """The chunks' tangential values as (n_pix, 2 n_el), column 2j + a (whole elements per chunk,
    pixels sorted within each column, as the scalar T)."""
    rows, cols, vals = [], [], []
    for r in results:
        elements, starts, pix, tval = r[0], r[1], r[2], r[8]
        col = np.repeat(elements, np.diff(starts))
        for a in range(2):
            rows.append(pix)
            cols.append(2 * col + a)
            vals.append(tval[:, a])
    if not rows:
        return sp.csr_matrix((n_pix, 2 * n_el))
    T = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_pix, 2 * n_el)).tocsr()
    T.eliminate_zeros()
    return T


def _spins(elem: np.ndarray, turn: bool = True) -> np.ndarray:
    """Per sample (sorted by element) a turn of the disk pattern and a shift of the square
    pattern, from the sample's rank within its element (R2 sequence: the turns of an
    element's samples are evenly spread): (S, 4) cos, sin, shift_x, shift_y.  With the
    same points for every sample (``turn=False``, transfer-2) an element's lens error does
    not average out over its surface samples: at 1024 x 1024 pixels the blurred mirror
    views kept ~2 % L1 however many surface samples they had."""
    if len(elem) == 0 or not turn:
        return np.column_stack([np.ones(len(elem)), np.zeros((len(elem), 3))])
    first = np.concatenate([[0], np.flatnonzero(np.diff(elem)) + 1])
    rank = np.arange(len(elem)) - np.repeat(first, np.diff(np.concatenate([first, [len(elem)]])))
    turn = 2 * np.pi * ((rank * 0.6180339887498949) % 1.0)
    return np.ascontiguousarray(np.column_stack([np.cos(turn), np.sin(turn), (rank * 0.7548776662466927) % 1.0,
                                                 (rank * 0.5698402909980532) % 1.0]))


def _element_chunks(elem: np.ndarray, rays: np.ndarray, rays_per_chunk: int) -> list[tuple[int, int]]:
    """Split samples (sorted by element) into ranges of whole elements of about
    ``rays_per_chunk`` rays each (an element with more rays is a chunk of its own)."""
    if len(elem) == 0:
        return []
    bounds = np.flatnonzero(np.diff(elem)) + 1  # where a new element starts
    el_start = np.concatenate([[0], bounds])
    el_end = np.concatenate([bounds, [len(elem)]])
    el_rays = np.add.reduceat(rays, el_start)
    chunks, a, acc = [], 0, 0
    for i in range(len(el_start)):
        acc += int(el_rays[i])
        if acc >= rays_per_chunk or i == len(el_start) - 1:
            chunks.append((int(el_start[a]), int(el_end[i])))
            a, acc = i + 1, 0
    return chunks


def _lens_view(surface: Surface, view: View, scene: OcclusionScene, s: LensSampling, eps: float,
               rays_per_batch: int, threads: int, progress: Callable[[float], None] | None,
               checkpoint: "Checkpoint | None", view_index: int,
               tree: "visibility.LazyTree | None" = None,
               turn_patterns: bool = True, emission: Profile | None = None) -> tuple:
    """One view's T by the lens estimator: chunks of whole elements cast on ``threads``
    threads, columns placed by element (independent of which thread finished first).
    Returns T, column errors, stats and the tangential matrix (None when the term is off)."""
    cam = view.camera
    n_pix = cam.nx * cam.ny
    shape = (n_pix, surface.n_elements)
    plan = ((checkpoint.plan(view_index) if checkpoint is not None else None)
            or _lens_plan(surface, view, s, rays_per_batch, tree, eps, turn_patterns, emission))
    err = np.zeros(surface.n_elements)
    if plan is None or not plan.chunks or scene.native is None:
        if plan is not None and plan.chunks and scene.native is None:
            raise ValueError("nothing to cast against: the scene has no triangles")
        tan = sp.csr_matrix((n_pix, 2 * surface.n_elements)) if emission is not None and emission.has_tangent else None
        return sp.csr_matrix(shape), err, {"rays": 0.0, "surface_samples": 0.0, "rays_evaluated": 0.0}, tan
    run = _lens_runner(view, scene, plan, eps)
    rays_of = [int(plan.n_lens[a:b].sum()) for a, b in plan.chunks]
    if checkpoint is not None and not 0 < checkpoint.rays_per_block < plan.rays:
        checkpoint = None  # a view smaller than one block is not worth files
    results: list = [None] * len(plan.chunks)
    done = reported = 0
    pool = ThreadPoolExecutor(threads) if threads > 1 else None
    try:
        for block in _blocks(rays_of, checkpoint.rays_per_block if checkpoint else 0):
            spans = [plan.chunks[i] for i in block]  # sample ranges: what the block holds, whatever the chunking
            saved = checkpoint.load(view_index, spans) if checkpoint else None
            if saved is not None and len(saved) == len(block):
                finished = zip(block, saved)
            else:
                work = [plan.chunks[i] for i in block]
                finished = zip(block, pool.map(run, work) if pool is not None else map(run, work))
            for i, r in finished:  # in chunk order, whatever thread finished first
                results[i] = r
                done += rays_of[i]
                if progress and (done - reported >= plan.rays / 100 or done >= plan.rays):
                    progress(min(done / plan.rays, 1.0))  # at most ~100 reports a view (they may cross processes)
                    reported = done
            if checkpoint and saved is None:
                checkpoint.save(view_index, spans, [results[i] for i in block])
    finally:
        if pool is not None:  # on Ctrl-C: drop the queued chunks, let the running ones end (milliseconds)
            pool.shutdown(wait=True, cancel_futures=True)
    # chunks hold increasing, whole elements: their columns concatenate into CSC
    nnz_per_col = np.zeros(surface.n_elements, np.int64)
    for elements, starts, _, _, col_err, *_ in results:
        nnz_per_col[elements] = np.diff(starts)
        err[elements] = col_err
    indptr = np.concatenate([[0], np.cumsum(nnz_per_col)])
    pix = np.concatenate([r[2] for r in results])
    val = np.concatenate([r[3] for r in results])
    T = sp.csc_matrix((val, pix, indptr), shape=shape)
    T.eliminate_zeros()
    stats = {"rays": float(sum(r[5] for r in results)), "surface_samples": float(len(plan.points_mm)),
             "rays_evaluated": float(sum(r[6] for r in results))}
    tan = _tangent_csr(results, n_pix, surface.n_elements) if len(plan.tang) else None
    return T.tocsr(), err, stats, tan


_NO_RECORD = np.zeros((0, 7), np.float32)


def _lens_runner(view: View, scene: OcclusionScene, plan: _LensPlan, eps: float) -> Callable[[tuple[int, int]], tuple]:
    """``run(chunk)``: cast one chunk ``(s0, s1)`` of ``plan`` (any thread: scratch per thread);
    its result is (elements, column starts, pixels, values, column errors, rays cast, rays, -)."""
    from . import transfer_kernel  # numba: imported when T is built, not by every command

    cam = view.camera
    n_pix = cam.nx * cam.ny
    nat = scene.native
    camera = transfer_kernel.camera_record(cam)
    mirror = transfer_kernel.mirror_record(view.mirror)
    ap_dist = np.array([a.distance_mm for a in cam.apertures], float)
    ap_r2 = np.array([a.radius_mm**2 for a in cam.apertures], float)
    scratch = threading.local()

    def run(chunk: tuple[int, int]):
        if not hasattr(scratch, "even"):
            scratch.even, scratch.odd = np.zeros(n_pix), np.zeros(n_pix)
            scratch.mark, scratch.touched = np.zeros(n_pix, np.bool_), np.zeros(n_pix, np.int32)
            scratch.tan = np.zeros((n_pix if len(plan.tang) else 0, 2))
        return transfer_kernel.lens_columns(
            nat.occluded16, nat.scene, camera, mirror, ap_dist, ap_r2, eps, plan.points_mm, plan.normals,
            plan.edges_mm, plan.ray_area_mm2, plan.element, plan.box_lo_mm, plan.box_hi_mm, plan.disk_center_mm,
            plan.disk_radius_mm, plan.use_box, plan.n_lens, plan.pat_off, plan.disk_unit,
            plan.square_unit, plan.jitter, chunk[0], chunk[1], n_pix, cam.nx, cam.ny,
            scratch.even, scratch.odd, scratch.mark, scratch.touched, _NO_RECORD, plan.clear, plan.margin_mm,
            plan.target, plan.n_cap, plan.spin, plan.emis, plan.tang, scratch.tan, plan.tframe)

    return run


# ------------------------------------------------------------------ one block at a time (cluster tasks)
def lens_plan(surface: Surface, view: View, s: LensSampling, rays_per_batch: int, occluders: list[Surface] | None = None,
              ray_offset_mm: float = 1e-3, emission: Profile | None = None) -> _LensPlan | None:
    """One view's lens-estimator plan (surface samples, their lens regions, the chunks of whole
    elements), the same :func:`build_transfer` makes; None when no face can reach the lens.
    With ``occluders`` (the scene's other blocking geometry) it also marks the faces whose
    segments are provably clear, so that casting it skips them (the same bytes either way)."""
    tree = None
    if occluders is not None:
        v, f = merge(surface, *occluders)
        tree = visibility.LazyTree(v, f, _piece_mm(surface, v)) if len(f) else None
    return _lens_plan(surface, view, s, rays_per_batch, tree, ray_offset_mm, emission=emission)


def lens_chunks(plan: _LensPlan | None) -> tuple[list[tuple[int, int]], list[int]]:
    """A view's chunks (sample spans of whole elements, the unit one thread casts) and the
    rays of each: what :func:`lens_blocks` groups."""
    if plan is None:
        return [], []
    return list(plan.chunks), [int(plan.n_lens[a:b].sum()) for a, b in plan.chunks]


def lens_blocks(chunks: list[tuple[int, int]], chunk_rays: list[int], rays_per_block: int) -> list[list[tuple[int, int]]]:
    """The checkpoint blocks of one view (from :func:`lens_chunks`): per block its chunks'
    sample spans, exactly what :func:`build_transfer` hands ``Checkpoint.load``/``save`` with
    this ``rays_per_block``; [] when it keeps no blocks for the view (less than one block)."""
    if not chunks or not 0 < rays_per_block < sum(chunk_rays):
        return []
    return [[chunks[i] for i in block] for block in _blocks(list(chunk_rays), rays_per_block)]


def cast_lens_block(view: View, scene: OcclusionScene, plan: _LensPlan, eps: float, spans: list[tuple[int, int]],
                    progress: Callable[[float], None] | None = None) -> list:
    """Cast one block (an entry of :func:`lens_blocks`) of ``plan`` (:func:`lens_plan`) on this thread: per chunk the result
    :func:`build_transfer` gets for it, in the form ``Checkpoint.save`` takes (the chunks'
    numbers do not depend on where or in which order they are cast: no random stream, fixed
    sample patterns).  ``scene`` is ``OcclusionScene(*merge(surface, *occluders))``;
    ``progress`` gets the fraction of the block's rays done after each chunk."""
    run = _lens_runner(view, scene, plan, eps)
    rays_of = [int(plan.n_lens[a:b].sum()) for a, b in spans]
    out, done = [], 0
    for span, rays in zip(spans, rays_of):
        out.append(run(span))
        done += rays
        if progress:
            progress(done / max(sum(rays_of), 1))
    return out


def _blocks(rays_of: list[int], rays_per_block: int) -> list[list[int]]:
    """Consecutive chunk indices grouped into checkpoint blocks of at least ``rays_per_block``
    rays (one block of everything when 0)."""
    if rays_per_block <= 0:
        return [list(range(len(rays_of)))] if rays_of else []
    out, cur, acc = [], [], 0
    for i, r in enumerate(rays_of):
        cur.append(i)
        acc += r
        if acc >= rays_per_block:
            out.append(cur)
            cur, acc = [], 0
    if cur:
        out.append(cur)
    return out


def _pairwise_pairs(surface: Surface, view: View, s: PairwiseSampling, rays_per_batch: int,
                    emission: Profile | None = None) -> Iterator[tuple]:
    cam = view.camera
    faces = _candidate_faces(surface, view)
    if len(faces) == 0:
        return
    n_sub = np.full(len(faces), s.surface_subdivisions)
    points, normals, element, area_share, _, face = sample_faces(surface, faces, n_sub, return_faces=True)
    depth = cam.axial(points)
    front = (depth > 0) & (np.einsum("ij,ij->i", normals, cam.center_mm - points) > -cam.aperture_radius_mm)
    points, normals, element, area_share, depth, face = (points[front], normals[front], element[front],
                                                         area_share[front], depth[front], face[front])
    frames = _frames(surface, face, emission)
    sub = s.pixel_subdivisions  # sub-pixels per pixel along each axis
    sub_pitch = cam.focal_pixel_mm / sub
    dA_vd = sub_pitch**2
    u, R = cam.focus_distance_mm, cam.aperture_radius_mm
    # the lines from a point through the lens disk meet the focal plane in a disk
    centre = cam.focal_plane_hit(points, np.broadcast_to(cam.center_mm, points.shape), depth)
    radius = R * np.abs(1 - u / depth)
    ccol, crow = cam.pixel_coords(centre)
    ccol, crow = ccol * sub, crow * sub  # in sub-pixel units
    rs = radius / sub_pitch
    c0 = np.clip(np.floor(ccol - rs - 0.5).astype(int), 0, cam.nx * sub - 1)
    c1 = np.clip(np.ceil(ccol + rs - 0.5).astype(int), 0, cam.nx * sub - 1)
    r0 = np.clip(np.floor(crow - rs - 0.5).astype(int), 0, cam.ny * sub - 1)
    r1 = np.clip(np.ceil(crow + rs - 0.5).astype(int), 0, cam.ny * sub - 1)
    onsensor = (ccol + rs >= 0) & (ccol - rs <= cam.nx * sub) & (crow + rs >= 0) & (crow - rs <= cam.ny * sub)
    wc, wr = c1 - c0 + 1, r1 - r0 + 1
    box = np.where(onsensor, wc * wr, 0)
    order = np.argsort(box, kind="stable")
    order = order[box[order] > 0]
    o = cam.center_mm + u * cam.axis
    yield int(np.sum(box[order]))  # first: the pairs to come (for progress), then the batches
    a = 0
    while a < len(order):
        # homogeneous chunk: samples with similar box sizes
        first = max(1, rays_per_batch // int(box[order[a]]))
        bmax = int(box[order[min(len(order), a + first) - 1]])  # sorted: the chunk's largest
        chunk = max(1, rays_per_batch // bmax)
        i = order[a:a + chunk]
        bw, bh = int(wc[i].max()), int(wr[i].max())
        a += len(i)
        dc, dr = np.meshgrid(np.arange(bw), np.arange(bh))
        cc = (c0[i, None] + dc.ravel()[None]).ravel()
        rr = (r0[i, None] + dr.ravel()[None]).ravel()
        rep = bw * bh
        ii = np.repeat(i, rep)
        inbox = (cc <= np.repeat(c1[i], rep)) & (rr <= np.repeat(r1[i], rep))
        X = o + sub_pitch * (((cc + 0.5) - cam.nx * sub / 2)[:, None] * cam.right
                             + ((rr + 0.5) - cam.ny * sub / 2)[:, None] * cam.down)
        p, nn, zz = points[ii], normals[ii], depth[ii]
        # the line's crossing of the lens plane (axial 0): from X (axial u) towards p
        with np.errstate(divide="ignore", invalid="ignore"):
            L = X + (u / (u - zz))[:, None] * (p - X)
            rl = L - cam.center_mm
            in_lens = inbox & (np.einsum("ij,ij->i", rl, rl) <= R * R)
            d = L - p
            dl = np.linalg.norm(d, axis=1)
            cos_s = np.einsum("ij,ij->i", nn, d) / dl
            cos_d = np.abs(d @ cam.axis) / dl
            dv = X - p
            r2 = np.einsum("ij,ij->i", dv, dv)
            w = np.where(in_lens & (cos_s > 0), cos_s * cos_d / (np.pi * r2), 0.0) * dA_vd * area_share[ii]
            wt = None
            if emission is not None and emission.has_tangent:  # along the ray leaving the real surface
                wt = ((w * emission.tangent_weight(np.where(in_lens, cos_s, 0.0)) / dl)[:, None]
                      * np.einsum("ij,iaj->ia", d, frames[ii]))  # in the face's frame
            if emission is not None and not emission.is_lambertian:  # theta_s at the real surface, both views
                w = w * emission.weight(np.where(in_lens, cos_s, 0.0))
        pix = (rr // sub) * cam.nx + (cc // sub)
        pix = np.where(inbox, pix, -1)
        yield p, nn, L, pix, w, element[ii], zz, len(i), len(ii), wt


class Checkpoint:
    """Where a long single-pose build keeps finished blocks of chunks, so that an
    interrupted build resumes (the pipeline keeps them as atomic files beside the T cache).

    ``load(view, spans)`` returns the saved chunk results of the block whose chunks cover the
    sample ranges ``spans`` [(s0, s1), ...], or None; ``save(view, spans, results)`` stores them.  ``rays_per_block``: how much work a block
    holds (0: no checkpoints).  Blocks depend only on the inputs, so a resumed build makes
    the same bytes as an uninterrupted one.
    """

    rays_per_block: int = 0

    def load(self, view: int, spans: list[tuple[int, int]]):  # pragma: no cover - interface
        return None

    def save(self, view: int, spans: list[tuple[int, int]], results: list) -> None:  # pragma: no cover - interface
        pass

    def plan(self, view: int):
        """The view's plan if it was already made (:func:`lens_plan` with the same inputs, e.g.
        while a cluster cast the blocks), else None: the build makes it."""
        return None


def default_threads() -> int:
    """Threads one T build may use: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def build_transfer(
    surface: Surface,
    views: list[View],
    occluders: list[Surface] = (),
    *,
    estimator: str = "lens",
    lens_sampling: LensSampling = LensSampling(),
    pairwise_sampling: PairwiseSampling = PairwiseSampling(),
    ray_offset_mm: float = 1e-3,
    rays_per_batch: int = 100_000,
    progress: Callable[[float], None] | None = None,
    threads: int | None = None,
    checkpoint: Checkpoint | None = None,
    skip_clear: bool = True,
    turn_patterns: bool = True,
    emission: Profile | None = None,
) -> TransferResult:
    """Compute T for ``surface`` seen by ``views``, with ``surface`` and ``occluders`` blocking.

    Parameters
    ----------
    surface : the placed subject surface (its faces both emit and occlude).
    views : the direct view and one per mirror (see :func:`views_for`).
    occluders : other blocking geometry (stage plate, mirror plates).
    rays_per_batch : rays per chunk of whole elements (the unit of work of one thread).
    progress : called with the fraction done (0..1) after every chunk of rays, for a progress bar.
    threads : threads casting rays (default: the cores available); the result does not depend on it.
    checkpoint : keeps finished blocks of a long build (lens estimator), see :class:`Checkpoint`.
    skip_clear : lens estimator: do not cast the rays of faces whose every segment to the lens
        is provably clear (:mod:`fluxcli.optics.visibility`); T is the same to the bit either way.
    turn_patterns : lens estimator: turn each surface sample's lens pattern by its own angle
        (False: the same lens points for every sample, as transfer-2 did; for the benchmark's
        before/after figures).
    emission : the surface's angular emission profile (:mod:`fluxcli.optics.emission`); None or
        Lambertian leaves every ray's weight (and T's bytes) as without one.

    Returns
    -------
    TransferResult with ``T`` of shape (nx * ny, n_elements), dimensionless, and per column
    an estimate of its L1 error (``column_error``, same unit as T; NaN for ``pairwise``).
    """
    if estimator not in ("lens", "pairwise"):
        raise ValueError(f"unknown estimator {estimator!r} (lens or pairwise)")
    threads = threads or default_threads()
    v, f = merge(surface, *occluders)
    scene = OcclusionScene(v, f)
    tree = None
    if estimator == "lens" and skip_clear and len(f):
        tree = visibility.LazyTree(v, f, _piece_mm(surface, v))
    n_pix = views[0].camera.nx * views[0].camera.ny
    shape = (n_pix, surface.n_elements)
    per_view, errors, stats, tangents = [], [], {}, []
    for i_view, view in enumerate(views):
        def sub(fraction, i_view=i_view):
            if progress:
                progress((i_view + fraction) / len(views))

        if estimator == "lens":
            T, err, st, tan = _lens_view(surface, view, scene, lens_sampling, ray_offset_mm, rays_per_batch, threads,
                                         sub, checkpoint, i_view, tree, turn_patterns, emission)
        else:
            T, st, tan = _pairwise_view(surface, view, scene, pairwise_sampling, ray_offset_mm, rays_per_batch, shape,
                                        sub, emission)
            err = np.full(surface.n_elements, np.nan)
        per_view.append(T)
        tangents.append(tan)
        errors.append(err)
        stats[view.name] = st
        sub(1.0)
    if emission is not None and emission.body_curvature:  # the body's own curvature, per element and view
        from .body_curvature import view_factors

        for k, fac in enumerate(view_factors(surface, views, emission)):
            per_view[k] = sp.csr_matrix(per_view[k] @ sp.diags(fac))
            errors[k] = errors[k] * fac
        if emission.has_tangent:  # its tangential flux too (columns 2j + a of element j)
            for k, fac in enumerate(view_factors(surface, views, emission, tangential=True)):
                if tangents[k] is not None:
                    tangents[k] = sp.csr_matrix(tangents[k] @ sp.diags(np.repeat(fac, 2)))
    total = per_view[0] * views[0].weight
    for T, view in zip(per_view[1:], views[1:]):
        total = total + T * view.weight
    # the views' errors add at most (triangle inequality)
    total_err = sum(e * view.weight for e, view in zip(errors, views))
    total_tan = None
    if emission is not None and emission.has_tangent:
        total_tan = tangents[0] * views[0].weight
        for Tt, view in zip(tangents[1:], views[1:]):
            total_tan = total_tan + Tt * view.weight
        total_tan = total_tan.tocsr()
    return TransferResult(list(views), per_view, total.tocsr(), stats, errors, total_err, total_tan,
                          tangents if total_tan is not None else [])


def _piece_mm(surface: Surface, vertices_mm: np.ndarray) -> float:
    """Occluders are cut into pieces about the size of the subject's faces (a ball around a
    whole stage plate would touch every lens cone), but no finer than 1/64 of the scene."""
    tri = surface.face_vertices_mm
    edge = float(np.median(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1))) if len(tri) else 1.0
    extent = float(np.ptp(vertices_mm, axis=0).max()) if len(vertices_mm) else 1.0
    return max(2 * edge, extent / 64)


def _pairwise_view(surface: Surface, view: View, scene: OcclusionScene, s: PairwiseSampling, eps: float,
                   rays_per_batch: int, shape: tuple[int, int], progress,
                   emission: Profile | None = None) -> tuple[sp.csr_matrix, dict]:
    filt = _PairFilter(view, scene, eps)
    gen = _pairwise_pairs(surface, view, s, rays_per_batch, emission)
    todo = next(gen, 0)  # the generator announces how many pairs it will evaluate
    done, n_samples = 0, 0
    parts, tparts = [], []
    for P, N, L, pix, w, elem, zz, n_s, n_rays, wt in gen:
        n_samples += n_s
        done += n_rays
        pix, elem, w = filt(P, N, L, pix, w, elem, zz)
        parts.append((pix, elem, w))
        if wt is not None:
            tparts.append((pix, elem, wt[filt.kept]))
        if todo:
            progress(min(done / todo, 1.0))
    # one COO -> CSR conversion (duplicates summed once, in a fixed order)
    pix = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    elem = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.int64)
    w = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0)
    T = sp.coo_matrix((w, (pix, elem)), shape=shape).tocsr()
    T.sum_duplicates()
    T.eliminate_zeros()
    tan = None
    if emission is not None and emission.has_tangent:
        rows = [p for p, _, _ in tparts for _ in range(2)]
        cols = [2 * e + a for _, e, _ in tparts for a in range(2)]
        vals = [t[:, a] for _, _, t in tparts for a in range(2)]
        tan = sp.coo_matrix((np.concatenate(vals) if vals else np.zeros(0),
                             (np.concatenate(rows) if rows else np.zeros(0, np.int64),
                              np.concatenate(cols) if cols else np.zeros(0, np.int64))),
                            shape=(shape[0], 2 * shape[1])).tocsr()
        tan.sum_duplicates()
        tan.eliminate_zeros()
    return T, {"rays": float(filt.rays_cast), "surface_samples": float(n_samples), "rays_evaluated": float(done)}, tan


def views_for(camera: ThinLensCamera, mirrors: list[tuple[str, PlaneMirror, float]]) -> list[View]:
    """The direct view plus one virtual camera per (name, mirror, weight)."""
    return [View("direct", camera)] + [View(name, camera.mirrored(m), m, w) for name, m, w in mirrors]
