"""Regions of interest on the surface: which elements they hold, and their numbers.

A region is a set of elements of the subject's surface *at rest* (before any pose), so
the same region is measured in every pose, every session and every filter.  Kinds:

- ``sphere`` {center_mm, radius_mm}, ``box`` {min_mm, max_mm}: an element belongs when its
  area-weighted centroid lies inside;
- ``disc`` {center_mm, radius_mm}: a geodesic disc around the surface point nearest
  ``center_mm``: an element belongs when the geodesic distance (over the mesh) from that
  point to its centroid is at most the radius (:func:`geodesic_distance_mm`);
- ``threshold`` {fraction}: the elements whose exitance is at least ``fraction`` of the
  peak's, connected to the peak element (sharing a vertex) through such elements — the
  automatic contour labs know, drawn on the map it measures;
- ``cell_array`` {array, value}: the elements whose integer cell array equals ``value``;
- ``elements`` {ids}: an explicit list (the mesh file's element ids when it has them,
  else indices from 0).

Per region (:func:`measure`): the total in photons/s with σ = √(wᵀCw) from the
reconstruction's covariance (never the sum of per-element σ), mean and peak radiance, its
area, and the shares of its area that are observed and well observed.

Radiance: fluxmap reconstructs the power per element; exitance M = b / (S t); the
radiance reported is the Lambertian one, L = M / π (photons s⁻¹ cm⁻² sr⁻¹,
:func:`fluxcli.surface.units.lambertian_radiance_per_cm2`).  With another emission profile
p(θ) (``subject.emission``) the radiance along the normal is M · p(0); L = M/π is what
image-based tools report and what is comparable between set-ups.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..surface.units import lambertian_radiance_per_cm2

KINDS = ("sphere", "disc", "box", "threshold", "cell_array", "elements")
MOSTLY = 0.5  # an ROI with less than this share of its area (well) observed says so


@dataclass(frozen=True)
class Region:
    """One region of interest (lengths in mm, in the subject's own frame at rest)."""

    name: str
    kind: str
    center_mm: tuple | None = None
    radius_mm: float | None = None
    min_mm: tuple | None = None
    max_mm: tuple | None = None
    fraction: float | None = None
    array: str | None = None
    value: int | None = None
    ids: tuple | None = None

    @property
    def needs_map(self) -> bool:
        """Drawn on the reconstructed map (differs per map), not on the geometry."""
        return self.kind == "threshold"


# ------------------------------------------------------------------ membership
def members(region: Region, surface, *, exitance=None, cell_array=None) -> np.ndarray:
    """(n_elements,) bool: the elements of ``surface`` (at rest) in ``region``.

    ``exitance`` (n_elements,) per mm², NaN where unobserved: for ``threshold``;
    ``cell_array`` (n_elements,) int: the values of ``region.array`` per element."""
    n = surface.n_elements
    if region.kind in ("sphere", "box"):
        c = surface.element_centroids_mm
        if region.kind == "sphere":
            return np.sum((c - np.asarray(region.center_mm, float)) ** 2, axis=1) <= float(region.radius_mm) ** 2
        return np.all((c >= np.asarray(region.min_mm, float)) & (c <= np.asarray(region.max_mm, float)), axis=1)
    if region.kind == "disc":
        return element_geodesic_mm(surface, np.asarray(region.center_mm, float)) <= float(region.radius_mm)
    if region.kind == "threshold":
        return threshold_members(exitance, surface.element_adjacency(), float(region.fraction))
    if region.kind == "cell_array":
        return np.asarray(cell_array) == int(region.value)
    if region.kind == "elements":
        ids = np.asarray(region.ids)
        known = np.asarray(surface.element_ids) if surface.element_ids is not None else np.arange(n)
        return np.isin(known, ids)
    raise ValueError(f"unknown ROI kind {region.kind!r} (one of {', '.join(KINDS)})")


def threshold_members(exitance, adjacency, fraction: float) -> np.ndarray:
    """Elements at or above ``fraction`` of the peak exitance, connected to the peak element
    through such elements (``adjacency``: elements sharing a vertex).  NaN (unobserved)
    never belongs; no finite positive value: no element."""
    e = np.asarray(exitance, float)
    ok = np.isfinite(e)
    if not ok.any() or np.nanmax(e) <= 0:
        return np.zeros(e.size, bool)
    peak = int(np.nanargmax(e))
    above = ok & (np.where(ok, e, -np.inf) >= fraction * e[peak])
    idx = np.flatnonzero(above)
    sub = sp.csr_matrix(adjacency)[idx][:, idx]
    _, label = connected_components(sub, directed=False)
    out = np.zeros(e.size, bool)
    out[idx[label == label[np.searchsorted(idx, peak)]]] = True
    return out


# ------------------------------------------------------------------ geodesic distance
def geodesic_distance_mm(vertices_mm, faces, source_mm) -> np.ndarray:
    """Geodesic distance (mm) over a triangle mesh from the surface point nearest
    ``source_mm`` to every vertex: Dijkstra's order with the planar triangle update of the
    fast marching method (Kimmel & Sethian 1998): a vertex is reached across a triangle
    whose other two vertices are known, from the virtual source unfolded into that
    triangle's plane, else along an edge.  First order: the error shrinks with the edge
    length, where plain Dijkstra on edges keeps a metrication error (up to ~8 % on a
    regular grid) at any refinement.  Unreachable vertices (another component): inf."""
    v = np.asarray(vertices_mm, float)
    f = np.asarray(faces, np.int64)
    dist = np.full(len(v), np.inf)
    tri = v[f]
    q, _ = _closest_on_triangles(tri, np.asarray(source_mm, float))
    k = int(np.argmin(np.sum((q - source_mm) ** 2, axis=1)))
    heap = []
    for i in f[k]:
        dist[i] = float(np.linalg.norm(v[i] - q[k]))
        heapq.heappush(heap, (dist[i], int(i)))
    faces_of = [[] for _ in range(len(v))]
    for fi, (a, b, c) in enumerate(f):
        faces_of[a].append(fi)
        faces_of[b].append(fi)
        faces_of[c].append(fi)
    done = np.zeros(len(v), bool)
    while heap:
        d, i = heapq.heappop(heap)
        if done[i] or d > dist[i]:
            continue
        done[i] = True
        for fi in faces_of[i]:
            a, b, c = f[fi]
            for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):  # z: the vertex updated from x, y
                if done[z] or not (done[x] or x == i) or not np.isfinite(dist[x]):
                    continue
                cand = dist[x] + np.linalg.norm(v[z] - v[x])
                if np.isfinite(dist[y]) and done[y]:
                    cand = min(cand, _unfold(v[x], v[y], v[z], dist[x], dist[y]))
                if cand < dist[z]:
                    dist[z] = cand
                    heapq.heappush(heap, (cand, int(z)))
    return dist


def _unfold(pa, pb, pc, da: float, db: float) -> float:
    """Distance to ``pc`` from a source at distance ``da`` from ``pa`` and ``db`` from ``pb``,
    unfolded into the plane of the triangle on the far side of edge ab; inf when the
    straight path would not cross the edge ab (the edge update covers it)."""
    ab = pb - pa
    L = float(np.linalg.norm(ab))
    if L == 0:
        return np.inf
    ex = ab / L
    ac = pc - pa
    cx = float(ac @ ex)
    cy = float(np.linalg.norm(ac - cx * ex))
    sx = (da * da - db * db + L * L) / (2 * L)
    sy2 = da * da - sx * sx
    if sy2 < 0 or cy <= 0:
        return np.inf
    sy = -np.sqrt(sy2)
    x_cross = sx + (cx - sx) * (-sy) / (cy - sy)
    if not 0.0 <= x_cross <= L:
        return np.inf
    return float(np.hypot(cx - sx, cy - sy))


def _closest_on_triangles(tri: np.ndarray, p: np.ndarray):
    """Closest point on each triangle (F, 3, 3) to ``p``: (F, 3) points, (F,) distances."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    # candidates: the projection into the plane when inside, else the closest point of each edge
    n = np.cross(b - a, c - a)
    nn = np.maximum(np.sum(n * n, axis=1), 1e-300)
    proj = p - (np.sum((p - a) * n, axis=1) / nn)[:, None] * n
    def inside(x):
        s1 = np.sum(np.cross(b - a, x - a) * n, axis=1)
        s2 = np.sum(np.cross(c - b, x - b) * n, axis=1)
        s3 = np.sum(np.cross(a - c, x - c) * n, axis=1)
        return (s1 >= 0) & (s2 >= 0) & (s3 >= 0)

    def seg(x0, x1):
        d = x1 - x0
        t = np.clip(np.sum((p - x0) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0, 1)
        return x0 + t[:, None] * d

    cands = [np.where(inside(proj)[:, None], proj, np.inf), seg(a, b), seg(b, c), seg(c, a)]
    d = np.stack([np.sum((x - p) ** 2, axis=1) for x in cands])
    best = np.argmin(d, axis=0)
    q = np.stack(cands)[best, np.arange(len(tri))]
    return q, np.sqrt(d[best, np.arange(len(tri))])


def element_geodesic_mm(surface, source_mm, *, levels: int = 1) -> np.ndarray:
    """Geodesic distance (mm) from the surface point nearest ``source_mm`` to each element's
    centroid: :func:`geodesic_distance_mm` on the surface refined ``levels`` times (every
    face, elements or not: a path may cross a cap), then per element the area-weighted mean
    over its fine faces of their corners' mean (the distance is nearly linear across an
    element away from the source)."""
    fine, parent = surface.refined(levels)
    d = geodesic_distance_mm(fine.vertices_mm, fine.faces, source_mm)
    ok = fine.element_of_face >= 0
    face_d = d[fine.faces[ok]].mean(axis=1)
    area = fine.face_areas_mm2[ok]
    el = parent[fine.element_of_face[ok]]
    num = np.bincount(el, weights=face_d * area, minlength=surface.n_elements)
    den = np.bincount(el, weights=area, minlength=surface.n_elements)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


# ------------------------------------------------------------------ numbers
@dataclass(frozen=True)
class RoiNumbers:
    """One region measured on one map (a pose's, or all poses' jointly)."""

    total_photons_per_s: float  # over the observed elements of the region
    sigma_photons_per_s: float  # √(wᵀCw); NaN when the method gives no covariance
    mean_radiance: float  # photons s⁻¹ cm⁻² sr⁻¹ over its observed area (Lambertian L = M/π)
    peak_radiance: float  # of its brightest observed element
    area_mm2: float
    observed_share: float  # of its area
    well_observed_share: float
    n_elements: int

    @property
    def status(self) -> str:
        """'' when the number stands for the region; else what is wrong with it."""
        if self.n_elements == 0:
            return "empty: no element of the surface lies in it"
        if self.observed_share < MOSTLY:
            return (f"mostly unobserved: {self.observed_share:.0%} of its area is observed; the total counts that part "
                    "only (a lower bound)")
        if self.well_observed_share < MOSTLY:
            return (f"mostly poorly observed: {self.well_observed_share:.0%} of its area is well observed; "
                    "the total leans on the regulariser")
        return ""


def measure(member, power, observed, well_observed, areas_mm2, *, exposure_s: float,
            variance=np.nan) -> RoiNumbers:
    """The numbers of one region on one map.

    Parameters
    ----------
    member : (n,) bool, the region's elements.
    power : (n,) photons per exposure per element (NaN where unobserved).
    observed, well_observed : (n,) bool.
    areas_mm2 : (n,) element areas.
    exposure_s : the exposure (s) that turns photons per exposure into photons/s.
    variance : photons², wᵀCw of the region's total (per exposure), from
        ``covariance.variance_of(member)``; NaN when unknown.
    """
    m = np.asarray(member, bool)
    obs = m & np.asarray(observed, bool)
    well = m & np.asarray(well_observed, bool)
    S = np.asarray(areas_mm2, float)
    p = np.asarray(power, float)
    area = float(S[m].sum())
    total = float(np.nansum(np.where(obs, p, 0.0)))
    obs_area = float(S[obs].sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_m = total / (obs_area * exposure_s) if obs_area > 0 else np.nan
        peak_m = float(np.nanmax(p[obs] / S[obs])) / exposure_s if obs.any() else np.nan
    return RoiNumbers(
        total_photons_per_s=total / exposure_s,
        sigma_photons_per_s=float(np.sqrt(max(float(variance), 0.0))) / exposure_s if np.isfinite(variance) else np.nan,
        mean_radiance=float(lambertian_radiance_per_cm2(mean_m)),
        peak_radiance=float(lambertian_radiance_per_cm2(peak_m)),
        area_mm2=area,
        observed_share=obs_area / area if area > 0 else 0.0,
        well_observed_share=float(S[well].sum()) / area if area > 0 else 0.0,
        n_elements=int(m.sum()),
    )


CSV_COLUMNS = ("roi", "pose", "height_mm", "rotation_deg", "total_photons_per_s", "sigma_photons_per_s",
               "mean_radiance", "peak_radiance", "area_mm2", "observed_share", "well_observed_share")


def csv_text(rows: list[tuple[str, str, float, float, RoiNumbers]]) -> str:
    """``rois.csv``: one row per (roi, pose label, height_mm, rotation_deg, numbers); the joint
    row has pose ``joint`` and empty height and rotation."""
    import csv
    import io

    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for name, pose, h, r, x in rows:
        w.writerow([name, pose, "" if h is None else f"{h:g}", "" if r is None else f"{r:g}",
                    *(f"{v:.8g}" for v in (x.total_photons_per_s, x.sigma_photons_per_s, x.mean_radiance,
                                            x.peak_radiance, x.area_mm2, x.observed_share, x.well_observed_share))])
    return out.getvalue()


SPECTRUM_COLUMNS = ("roi", "filter", "transmission", "pose", "total_photons_per_s", "sigma_photons_per_s",
                    "mean_radiance", "observed_share", "well_observed_share")


def spectrum_csv_text(per_filter) -> str:
    """``rois_spectrum.csv``: per ROI, per filter (``(name, transmission, meter)`` with the
    meter's maps), the numbers of every map (poses and ``joint``) — the per-ROI spectrum."""
    import csv
    import io

    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(SPECTRUM_COLUMNS)
    rows = []
    for name, t, meter in per_filter:
        for roi, pose, _, _, x in meter.rows():
            rows.append((roi, name, t, pose, x))
    order = {n: i for i, (n, _, _) in enumerate(per_filter)}
    for roi, name, t, pose, x in sorted(rows, key=lambda r: (r[0], r[3], order[r[1]])):
        w.writerow([roi, name, f"{t:g}", pose, *(f"{v:.8g}" for v in (
            x.total_photons_per_s, x.sigma_photons_per_s, x.mean_radiance, x.observed_share, x.well_observed_share))])
    return out.getvalue()
