"""Carry exitance from the tetrahedral mesh boundary onto reconstruction elements.

The reconstruction surface and the tetrahedral boundary describe the same subject but
are different triangulations (fTetWild moves the boundary within a small envelope).
The exitance is sampled on the reconstruction faces at closest points on the tet
boundary, integrated per element, then rescaled so that no power is created or lost.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..surface.geometry import triangle_areas
from ..errors import InputError

__all__ = ["exitance_to_elements", "closest_points_on_triangles"]


def _subtriangle_centroids(n_sub):
    """Barycentric coordinates (n_sub², 3) of the centroids of a regular n_sub-split."""
    pts = []
    for i in range(n_sub):
        for j in range(n_sub - i):
            pts.append(((i + 1 / 3) / n_sub, (j + 1 / 3) / n_sub))
            if i + j <= n_sub - 2:
                pts.append(((i + 2 / 3) / n_sub, (j + 2 / 3) / n_sub))
    uv = np.array(pts)
    return np.column_stack([1 - uv.sum(axis=1), uv])


def _closest_on_triangle(p, a, b, c):
    """Barycentric coordinates of the point of triangle abc closest to p (Ericson 5.1.5).

    All arguments have shape (..., 3); returns (..., 3).
    """
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    dot = lambda u, v: np.einsum("...i,...i->...", u, v)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    v = np.select(conditions, [zero, one, t_ab, zero, zero, 1 - t_bc], v_in)
    w = np.select(conditions, [zero, zero, zero, one, t_ac, t_bc], w_in)
    return np.stack([1 - v - w, v, w], axis=-1)


def closest_points_on_triangles(points_mm, vertices_mm, faces, *, n_candidates=10):
    """Closest point of a triangle surface to each query point.

    Parameters
    ----------
    points_mm : ndarray, shape (n_points, 3)
        Query points in mm.
    vertices_mm : ndarray, shape (n_vertices, 3)
        Surface vertices in mm.
    faces : ndarray of int, shape (n_faces, 3)
        Surface triangles.
    n_candidates : int
        Triangles examined per point: those with the nearest centroids.  Exact when the
        closest triangle is among them, which holds for points near a reasonably
        uniform surface.

    Returns
    -------
    face_index : ndarray of int64, shape (n_points,)
        Closest triangle.
    barycentric : ndarray, shape (n_points, 3)
        Barycentric coordinates of the closest point in that triangle.
    distance_mm : ndarray, shape (n_points,)
        Distance to the surface in mm.
    """
    tri = vertices_mm[faces]
    k = min(n_candidates, len(faces))
    _, cand = cKDTree(tri.mean(axis=1)).query(points_mm, k=k)
    cand = cand.reshape(len(points_mm), k)
    t = tri[cand]  # (n, k, 3, 3)
    bary = _closest_on_triangle(points_mm[:, None, :], t[:, :, 0], t[:, :, 1], t[:, :, 2])
    closest = np.einsum("nki,nkij->nkj", bary, t)
    dist = np.linalg.norm(closest - points_mm[:, None, :], axis=2)
    best = np.argmin(dist, axis=1)
    rows = np.arange(len(points_mm))
    return cand[rows, best].astype(np.int64), bary[rows, best], dist[rows, best]


def exitance_to_elements(
    boundary_vertices_mm,
    boundary_faces,
    exitance_at_boundary_nodes,
    surface_vertices_mm,
    surface_faces,
    element_of_face,
    n_elements,
    *,
    n_subdivisions=3,
):
    """Integrate boundary exitance over reconstruction elements, conserving power.

    Parameters
    ----------
    boundary_vertices_mm : array_like, shape (n_boundary_nodes, 3)
        Vertices of the tetrahedral mesh boundary in mm
        (:meth:`DiffusionModel.boundary_surface`).
    boundary_faces : array_like of int, shape (n_boundary_faces, 3)
        Boundary triangles indexing ``boundary_vertices_mm``.
    exitance_at_boundary_nodes : array_like, shape (n_boundary_nodes,) or (n_boundary_nodes, n_sources)
        Exitance J in photons s⁻¹ mm⁻², linear over each boundary triangle.
    surface_vertices_mm : array_like, shape (n_vertices, 3)
        Reconstruction surface vertices in mm.
    surface_faces : array_like of int, shape (n_faces, 3)
        Reconstruction surface triangles.
    element_of_face : array_like of int, shape (n_faces,)
        Reconstruction element (0 … n_elements − 1) each face belongs to.
    n_elements : int
        Number of reconstruction elements; every element must own at least one face.
    n_subdivisions : int
        Each face is split into ``n_subdivisions²`` sub-triangles whose centroids are
        the quadrature points.

    Returns
    -------
    power_per_element : ndarray, shape (n_elements,) or (n_elements, n_sources)
        Power leaving through each element in photons/s.  Rescaled so that its sum is
        exactly the total exitance ∫ J dS over the tet boundary.
    exitance_per_element : ndarray, same shape
        ``power_per_element`` divided by element area, photons s⁻¹ mm⁻².

    Raises
    ------
    ValueError
        If shapes disagree, element indices are out of range, an element has no
        faces, or the sampled power vanishes while the total does not.
    """
    bv = np.asarray(boundary_vertices_mm, dtype=np.float64)
    bf = np.asarray(boundary_faces, dtype=np.int64)
    j_nodes = np.asarray(exitance_at_boundary_nodes, dtype=np.float64)
    sv = np.asarray(surface_vertices_mm, dtype=np.float64)
    sf = np.asarray(surface_faces, dtype=np.int64)
    element_of_face = np.asarray(element_of_face, dtype=np.int64)
    n_elements = int(n_elements)
    if bv.ndim != 2 or bv.shape[1] != 3 or bf.ndim != 2 or bf.shape[1] != 3 or len(bf) == 0:
        raise InputError("boundary surface must be vertices (n, 3) and faces (m, 3), m > 0.")
    if sv.ndim != 2 or sv.shape[1] != 3 or sf.ndim != 2 or sf.shape[1] != 3 or len(sf) == 0:
        raise InputError("reconstruction surface must be vertices (n, 3) and faces (m, 3), m > 0.")
    if j_nodes.shape[0] != len(bv) or j_nodes.ndim not in (1, 2):
        raise InputError(
            f"exitance must have one row per boundary vertex ({len(bv)}), got shape {j_nodes.shape}."
        )
    if element_of_face.shape != (len(sf),):
        raise InputError(f"element_of_face must have one entry per surface face ({len(sf)}).")
    if element_of_face.min() < 0 or element_of_face.max() >= n_elements:
        raise InputError(f"element_of_face must lie in 0 … {n_elements - 1}.")
    squeeze = j_nodes.ndim == 1
    j2 = j_nodes.reshape(len(bv), -1)

    # Exact total of the linear interpolant on the tet boundary.
    b_tri = bv[bf]
    b_area = triangle_areas(b_tri)
    total = b_area @ j2[bf].mean(axis=1)  # (n_sources,)

    # Sub-triangle centroid quadrature on the reconstruction faces.
    s_tri = sv[sf]
    s_area = triangle_areas(s_tri)
    q_bary = _subtriangle_centroids(int(n_subdivisions))
    points = np.einsum("qi,fij->fqj", q_bary, s_tri).reshape(-1, 3)
    face_idx, bary, _ = closest_points_on_triangles(points, bv, bf)
    j_points = np.einsum("pi,pis->ps", bary, j2[bf[face_idx]])  # (n_points, n_sources)
    weight = np.repeat(s_area / len(q_bary), len(q_bary))
    owner = np.repeat(element_of_face, len(q_bary))
    raw = np.zeros((n_elements, j2.shape[1]))
    np.add.at(raw, owner, weight[:, None] * j_points)

    element_area = np.bincount(element_of_face, weights=s_area, minlength=n_elements)
    if np.any(element_area <= 0):
        raise InputError(f"{int(np.sum(element_area <= 0))} elements have no faces (zero area).")

    raw_sum = raw.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(total == 0, 0.0, total / raw_sum)
    if not np.all(np.isfinite(scale)):
        raise InputError("sampled exitance is zero on the surface although the total is not.")
    power = raw * scale
    exitance = power / element_area[:, None]
    if squeeze:
        return power[:, 0], exitance[:, 0]
    return power, exitance
