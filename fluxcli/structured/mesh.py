"""From triangulated points to a closed surface, and how far points lie from a reference.

Meshing (:func:`closed_surface`): an implicit function interpolating the oriented points
with a triharmonic radial basis function (the cubic kernel r^3 with a linear polynomial;
Carr et al. 2001: zero on the surface, +-d at +-d along the normals), intersected with the
half-space above the stage top (the subject rests on it) and with the points' bounding
box (ends no view saw are closed flat at the extent of what was seen), contoured at zero
(marching cubes, VTK), smoothed, decimated to a face size, and grouped into elements of
a target size.  What no view saw (the underside of a subject lying on the stage) is the
function's continuation: the cubic kernel continues the seen *curvature*, so a rounded
belly keeps curving in towards the stage.  Measured on the simulated rig (make
structured-light): the biharmonic kernel (r, which continues the seen slope) gave +4.4 %
volume and +2.5 % area on data-samples/mouse.vtk (its belly filled down to the stage),
the cubic kernel -0.5 % and -0.4 %; the lying cylinder -0.2 % and -1.2 %.  (A
nearest-tangent-plane distance, Hoppe et al. 1992, extended the lowest seen tangents
straight down: +14 % volume on the lying cylinder.)
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

from ..surface.geometry import triangle_areas
from ..surface.mesh import Surface

__all__ = ["estimate_normals", "remove_outliers", "closed_surface", "distances_to_surface", "coverage",
           "signed_volume_mm3", "capture_metrics"]


def estimate_normals(points_mm: np.ndarray, view_dirs: np.ndarray, *, k: int = 12) -> np.ndarray:
    """Unit normals (n, 3) of a point cloud by local PCA, turned to face the viewer
    (``view_dirs``: the direction each point was seen along, from the camera to the point)."""
    tree = cKDTree(points_mm)
    _, nb = tree.query(points_mm, k=min(k, len(points_mm)))
    q = points_mm[nb] - points_mm[nb].mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    return np.where(((n * view_dirs).sum(1) > 0)[:, None], -n, n)


def remove_outliers(points_mm: np.ndarray, *, k: int = 8, n_sigma: float = 3.0,
                    max_plane_distance_mm: float | None = None) -> np.ndarray:
    """Keep-mask (n,) of points whose mean distance to their ``k`` neighbours is within
    ``n_sigma`` robust standard deviations of the median (statistical outlier removal), and,
    when given, whose distance to the plane of their ``3k`` neighbours is below
    ``max_plane_distance_mm``."""
    tree = cKDTree(points_mm)
    d, nb = tree.query(points_mm, k=k + 1)
    mean_d = d[:, 1:].mean(1)
    med = np.median(mean_d)
    mad = 1.4826 * np.median(np.abs(mean_d - med))
    keep = mean_d <= med + n_sigma * max(mad, 1e-12)
    if max_plane_distance_mm is not None:
        _, nb = tree.query(points_mm, k=3 * k)
        c = points_mm[nb].mean(1)
        q = points_mm[nb] - c[:, None]
        _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
        dist = np.abs(((points_mm - c) * vec[:, :, 0]).sum(1))
        keep &= dist <= max_plane_distance_mm
    return keep


def closed_surface(points_mm: np.ndarray, normals: np.ndarray, *, floor_z_mm: float | None, voxel_mm: float = 0.6,
                   centre_spacing_mm: float = 1.5, offset_mm: float = 1.0, smoothing: float = 0.0, face_size_mm: float = 1.0, element_size_mm: float | None = None,
                   seed: int = 0, free_rays: tuple[np.ndarray, np.ndarray] | None = None,
                   free_margin_mm: float = 1.0, kernel: str = "cubic") -> Surface:
    """A closed, outward-wound triangle surface through oriented points.

    Parameters
    ----------
    points_mm, normals : (n, 3) points and their outward unit normals.
    floor_z_mm : the stage top the subject rests on (the surface is closed flat there), or None.
    voxel_mm : grid step on which the implicit function is contoured (mm).
    centre_spacing_mm : the points are thinned to one per cube of this side (mm) as RBF centres.
    offset_mm : off-surface constraints at +-this along the normals (mm).
    smoothing : RBF smoothing (0 interpolates).
    face_size_mm : target edge length of the output triangles (mm).
    free_rays : ``(points_mm, directions)`` of every decoded pixel (stage points included):
        the ray before the point it saw is empty space (space carving), up to
        ``free_margin_mm`` before the point; voxels so crossed are set outside.
    element_size_mm : target size of an element (faces are grouped by k-means on their
        centroids into ``area / element_size_mm**2`` elements); None: one element per face.
    kernel : the radial basis (scipy's RBFInterpolator names): ``cubic`` (r^3, triharmonic:
        continues the seen curvature) or ``linear`` (r, biharmonic: continues the seen slope).
    """
    import pyvista as pv

    from scipy.interpolate import RBFInterpolator

    lo, hi = points_mm.min(0), points_mm.max(0)
    if floor_z_mm is not None:
        lo[2] = min(lo[2], floor_z_mm)
    pad = 3 * voxel_mm
    dims = np.ceil((hi - lo + 2 * pad) / voxel_mm).astype(int) + 1
    grid = pv.ImageData(dimensions=dims, spacing=(voxel_mm,) * 3, origin=lo - pad)
    g = np.asarray(grid.points)
    # centres: one point per cell of centre_spacing_mm (the one nearest the cell's mean),
    # with off-surface companions at +-offset along the normal (Carr et al. 2001)
    cell = np.floor((points_mm - lo) / centre_spacing_mm).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    c, cn = points_mm[first], normals[first]
    centres = np.concatenate([c, c + offset_mm * cn, c - offset_mm * cn])
    values = np.concatenate([np.zeros(len(c)), np.full(len(c), offset_mm), np.full(len(c), -offset_mm)])
    rbf = RBFInterpolator(centres, values, kernel=kernel, degree=1, smoothing=smoothing)
    sdf = np.concatenate([rbf(g[a:a + 50000]) for a in range(0, len(g), 50000)])
    box = np.max(np.maximum(lo - g, g - hi), axis=1)  # > 0 outside the points' bounding box (and floor)
    sdf = np.maximum(sdf, box)
    if floor_z_mm is not None:
        sdf = np.maximum(sdf, floor_z_mm - g[:, 2])
    if free_rays is not None:
        sdf = np.where(_free_voxels(free_rays, lo - pad, dims, voxel_mm, free_margin_mm).ravel(order="F"),
                       np.maximum(sdf, 0.5 * voxel_mm), sdf)
    grid["sdf"] = sdf
    m = grid.contour([0.0], scalars="sdf", method="marching_cubes").triangulate().clean()
    with warnings.catch_warnings():  # connectivity's RegionId arrays go stale in extract_surface; dropped below
        warnings.simplefilter("ignore", getattr(pv, "InvalidMeshWarning", Warning))
        m = m.connectivity("largest").extract_surface(algorithm="dataset_surface").triangulate()
    m = pv.PolyData(np.asarray(m.points), m.faces).clean()  # the triangles alone (no stray lines, no stale arrays)
    m = m.smooth_taubin(n_iter=20, pass_band=0.1)
    target_faces = max(int(2 * m.area / (np.sqrt(3) / 4 * face_size_mm**2) / 2), 8)
    if m.n_cells > target_faces:
        m = m.decimate_pro(1 - target_faces / m.n_cells, preserve_topology=True).clean()
    m = m.compute_normals(auto_orient_normals=True, consistent_normals=True, split_vertices=False)
    verts = np.asarray(m.points, float)
    faces = np.asarray(m.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    # outward winding: positive signed volume
    t = verts[faces]
    if np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() < 0:
        faces = faces[:, ::-1]
    if element_size_mm is None:
        elem = np.arange(len(faces))
    else:
        from scipy.cluster.vq import kmeans2

        area = triangle_areas(t).sum()
        n_el = int(np.clip(round(area / element_size_mm**2), 1, len(faces)))
        cent = verts[faces].mean(1)
        _, elem = kmeans2(cent, n_el, minit="++", seed=seed)
        _, elem = np.unique(elem, return_inverse=True)
    return Surface(verts, faces, elem.astype(np.int64), int(elem.max()) + 1)


def _free_voxels(free_rays, origin_mm, dims, voxel_mm, margin_mm) -> np.ndarray:
    """Boolean grid ``dims`` (x fastest, as VTK's image data) of voxels a ray crossed before its point."""
    P, D = (np.asarray(a, float) for a in free_rays)
    free = np.zeros(tuple(dims), bool)
    extent = np.linalg.norm(dims * voxel_mm)
    for t in np.arange(margin_mm, margin_mm + extent, 0.5 * voxel_mm):
        q = np.round((P - t * D - origin_mm) / voxel_mm).astype(np.int64)
        ok = np.all((q >= 0) & (q < dims), axis=1)
        if not ok.any() and t > margin_mm + 2 * voxel_mm:
            break
        free[q[ok, 0], q[ok, 1], q[ok, 2]] = True
    return free


def distances_to_surface(points_mm: np.ndarray, surface: Surface) -> np.ndarray:
    """Unsigned distance (mm) of each point to the nearest point of a triangle surface (VTK's cell locator)."""
    import pyvista as pv

    faces = np.hstack([np.full((len(surface.faces), 1), 3), surface.faces]).ravel()
    ref = pv.PolyData(surface.vertices_mm, faces)
    _, closest = ref.find_closest_cell(points_mm, return_closest_point=True)
    return np.linalg.norm(points_mm - closest, axis=1)


def coverage(points_mm: np.ndarray, surface: Surface, *, radius_mm: float, samples_per_mm2: float = 4.0,
             seed: int = 0) -> float:
    """Fraction of ``surface``'s area within ``radius_mm`` of a point (area-uniform samples)."""
    rng = np.random.default_rng(seed)
    areas = surface.face_areas_mm2
    n = int(max(areas.sum() * samples_per_mm2, 1000))
    f = rng.choice(len(areas), size=n, p=areas / areas.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    t = surface.vertices_mm[surface.faces[f]]
    p = (1 - s)[:, None] * t[:, 0] + (s * (1 - r2))[:, None] * t[:, 1] + (s * r2)[:, None] * t[:, 2]
    d, _ = cKDTree(points_mm).query(p, distance_upper_bound=radius_mm)
    return float(np.mean(np.isfinite(d)))


def signed_volume_mm3(surface: Surface) -> float:
    """Enclosed volume (mm^3) of a closed, outward-wound triangle surface (divergence theorem)."""
    t = surface.vertices_mm[surface.faces]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)


def capture_metrics(points_mm: np.ndarray, distance_mm: np.ndarray, mesh: Surface, truth: Surface, *,
                    coverage_radius_mm: float = 1.0) -> dict:
    """How a structured-light capture compares with the true surface (simulated rig).

    Returns a dict of plain numbers: ``points``; ``within_0.1mm``, ``within_0.2mm``,
    ``within_0.4mm`` (fractions of points whose distance to the truth is below); their
    ``median_distance_mm``; ``covered_fraction_1mm`` (fraction of the true area within
    ``coverage_radius_mm`` of a point); the mesh's ``volume_mm3``, ``area_mm2``, the truth's,
    and the relative ``volume_error`` and ``area_error``; ``mesh_closed``."""
    d = np.asarray(distance_mm, float)
    vol, vol_true = signed_volume_mm3(mesh), signed_volume_mm3(truth)
    area, area_true = float(mesh.face_areas_mm2.sum()), float(truth.face_areas_mm2.sum())
    out = {"points": int(len(d))}
    for t in (0.1, 0.2, 0.4):
        out[f"within_{t}mm"] = float(np.mean(d < t)) if len(d) else 0.0
    out.update({"median_distance_mm": float(np.median(d)) if len(d) else float("nan"),
                "covered_fraction_1mm": coverage(points_mm, truth, radius_mm=coverage_radius_mm),
                "volume_mm3": vol, "volume_true_mm3": vol_true, "volume_error": vol / vol_true - 1,
                "area_mm2": area, "area_true_mm2": area_true, "area_error": area / area_true - 1,
                "mesh_closed": bool(mesh.is_closed)})
    return out
