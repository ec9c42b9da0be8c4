"""Which faces see the whole lens: a conservative cone test, so that their rays need no Embree query.

Every ray the ``lens`` estimator casts from a face runs from a point of the face (lifted by
the ray offset along its normal) to a point of the lens disk (or, for a mirror view, to the
mirror and on to the real lens).  All such segments lie inside the convex hull of two balls,
one around the face and one around the lens disk, and in front of the face's plane (and of
the mirror's plane).  When no occluding triangle reaches into that region, every one of the
face's segments is clear and casting them would only confirm it: :func:`clear_faces` finds
those faces with a bounding-volume hierarchy of the occluders, cut into small pieces so that
a big plate (the stage, a mirror) does not cover everything with one bounding ball.

The test is conservative (a face is called clear only when no triangle can touch any of its
segments, with a margin far above Embree's float32 rounding), so skipping the queries leaves
T bit for bit as it was (tests/test_transfer_kernel.py checks this).  It answers per face and
per segment: bit 1 = the surface -> lens (or surface -> mirror) segments are clear, bit 2 =
the mirror -> lens segments are clear.

Hull of two balls (c1, r1), (c2, r2): the union of the balls centred at c(t) = c1 + t (c2 - c1)
with radius r(t) = r1 + t (r2 - r1), 0 <= t <= 1 (convex, and it holds both balls); the
distance of a point x from it is min_t |x - c(t)| - r(t), a convex function of t whose
minimiser has a closed form.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numba as nb
import numpy as np

# Distances below this are treated as touching (mm): far above the rounding of float32 rays
# and vertices at the scene's coordinates (~1e-5 mm at 300 mm), far below any real clearance.
MARGIN_MM = 1e-5


@dataclass
class OccluderTree:
    """Occluding triangles cut into pieces no longer than ``piece_mm`` per edge, in a
    bounding-volume hierarchy (axis-aligned boxes, median splits, up to 4 pieces a leaf)."""

    pieces: np.ndarray  # (K, 3, 3) mm, in leaf order
    centre: np.ndarray  # (K, 3) bounding-ball centre of each piece
    radius: np.ndarray  # (K,) its radius
    lo: np.ndarray  # (M, 3) node box
    hi: np.ndarray  # (M, 3)
    child: np.ndarray  # (M,) first child (the second is child + 1), -1 for a leaf
    start: np.ndarray  # (M,) a leaf's first piece
    count: np.ndarray  # (M,) a leaf's pieces
    margin_mm: float


MAX_PIECES = 4_000_000  # the hierarchy holds at most ~this many pieces (~0.4 GB)

# Testing a face's cone costs about as much as casting a few hundred rays in packets: views
# with fewer rays per face than this are cast without the test.
MIN_RAYS_PER_FACE = 256


class LazyTree:
    """The :class:`OccluderTree` of a scene, built when first asked for (a build whose views all
    have too few rays per face for the test never builds it)."""

    def __init__(self, vertices_mm: np.ndarray, faces: np.ndarray, piece_mm: float):
        self._args, self._tree = (vertices_mm, faces, piece_mm), None

    def get(self) -> OccluderTree:
        if self._tree is None:
            self._tree = occluder_tree(*self._args)
        return self._tree


def occluder_tree(vertices_mm: np.ndarray, faces: np.ndarray, piece_mm: float) -> OccluderTree:
    """The hierarchy of every triangle of the scene (subject and other occluders)."""
    v = np.ascontiguousarray(vertices_mm, np.float64)
    f = np.ascontiguousarray(faces, np.int64)
    tri = v[f]
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1) if len(f) else np.zeros(0)
    n_sub = np.clip(np.ceil(longest / piece_mm), 1, 64).astype(np.int64)
    while np.sum(n_sub**2) > MAX_PIECES and np.any(n_sub > 1):  # bounded memory: coarser pieces
        piece_mm *= 1.5
        n_sub = np.clip(np.ceil(longest / piece_mm), 1, 64).astype(np.int64)
    pieces = _cut(tri, n_sub, int(np.sum(n_sub**2)))
    centre = pieces.mean(axis=1)
    radius = np.linalg.norm(pieces - centre[:, None], axis=2).max(axis=1) if len(pieces) else np.zeros(0)
    order, lo, hi, child, start, count = _build(pieces, centre)
    scale = float(np.abs(v).max()) if len(v) else 1.0
    return OccluderTree(np.ascontiguousarray(pieces[order]), np.ascontiguousarray(centre[order]),
                        np.ascontiguousarray(radius[order]), lo, hi, child, start, count,
                        MARGIN_MM + 2e-7 * scale)


@nb.njit(cache=True)
def _cut(tri, n_sub, total):
    out = np.empty((total, 3, 3))
    k = 0
    for t in range(len(tri)):
        n = n_sub[t]
        a, e0, e1 = tri[t, 0], (tri[t, 1] - tri[t, 0]) / n, (tri[t, 2] - tri[t, 0]) / n
        for i in range(n):
            for j in range(n - i):
                out[k, 0] = a + i * e0 + j * e1
                out[k, 1] = a + (i + 1) * e0 + j * e1
                out[k, 2] = a + i * e0 + (j + 1) * e1
                k += 1
                if i + j <= n - 2:
                    out[k, 0] = a + (i + 1) * e0 + j * e1
                    out[k, 1] = a + (i + 1) * e0 + (j + 1) * e1
                    out[k, 2] = a + i * e0 + (j + 1) * e1
                    k += 1
    return out


@nb.njit(cache=True)
def _build(pieces, centre):
    k = len(pieces)
    cap = max(1, 2 * k)
    lo = np.empty((cap, 3))
    hi = np.empty((cap, 3))
    child = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    order = np.arange(k)
    stack = np.empty((cap, 2), np.int64)  # (node, unused)
    n_nodes = 1
    start[0], count[0] = 0, k
    top = 0
    stack[0, 0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top, 0]
        a, b = start[node], start[node] + count[node]
        for d in range(3):
            lo[node, d] = np.inf
            hi[node, d] = -np.inf
        for i in range(a, b):
            for c in range(3):
                for d in range(3):
                    x = pieces[order[i], c, d]
                    lo[node, d] = min(lo[node, d], x)
                    hi[node, d] = max(hi[node, d], x)
        if b - a <= 4:
            continue
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for i in range(a, b):
            for d in range(3):
                cmin[d] = min(cmin[d], centre[order[i], d])
                cmax[d] = max(cmax[d], centre[order[i], d])
        axis = int(np.argmax(cmax - cmin))
        keys = np.empty(b - a)
        for i in range(a, b):
            keys[i - a] = centre[order[i], axis]
        sub = order[a:b][np.argsort(keys, kind="mergesort")]
        order[a:b] = sub
        mid = a + (b - a) // 2
        left = n_nodes
        n_nodes += 2
        child[node] = left
        start[left], count[left] = a, mid - a
        start[left + 1], count[left + 1] = mid, b - mid
        stack[top, 0] = left
        stack[top + 1, 0] = left + 1
        top += 2
    return order, lo[:n_nodes].copy(), hi[:n_nodes].copy(), child[:n_nodes].copy(), start[:n_nodes].copy(), \
        count[:n_nodes].copy()


@nb.njit(cache=True, inline="always")
def _hull_distance(x0, x1, x2, c1, r1, c2, r2):
    """Distance of a point from the hull of balls (c1, r1) and (c2, r2) (negative inside)."""
    d0, d1, d2 = c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2]
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    p0, p1, p2 = x0 - c1[0], x1 - c1[1], x2 - c1[2]
    q2 = p0 * p0 + p1 * p1 + p2 * p2
    best = min(math.sqrt(q2) - r1, math.sqrt((x0 - c2[0]) ** 2 + (x1 - c2[1]) ** 2 + (x2 - c2[2]) ** 2) - r2)
    if length > 0:
        s = (p0 * d0 + p1 * d1 + p2 * d2) / length
        h = math.sqrt(max(q2 - s * s, 0.0))
        k = -(r2 - r1) / length
        if abs(k) < 1:
            t = (s - k * h / math.sqrt(1 - k * k)) / length
            if 0 < t < 1:
                best = min(best, math.sqrt((s - t * length) ** 2 + h * h) - (r1 + t * (r2 - r1)))
    return best


@nb.njit(cache=True)
def _clear(lo, hi, child, start, count, pieces, centre, radius, c1, r1, c2, r2, planes, margin):
    """True when no piece reaches into the hull of the two balls in front of every plane
    (a piece wholly on or behind a plane, ``n . x <= d`` for all its points, cannot block)."""
    stack = np.empty(128, np.int64)
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        # behind a plane: max of n . x over the box
        behind = False
        for p in range(len(planes)):
            m = 0.0
            for d in range(3):
                m += planes[p, d] * (lo[node, d] + hi[node, d]) / 2 + abs(planes[p, d]) * (hi[node, d] - lo[node, d]) / 2
            if m <= planes[p, 3]:
                behind = True
                break
        if behind:
            continue
        b0, b1, b2 = (lo[node, 0] + hi[node, 0]) / 2, (lo[node, 1] + hi[node, 1]) / 2, (lo[node, 2] + hi[node, 2]) / 2
        rb = math.sqrt((hi[node, 0] - b0) ** 2 + (hi[node, 1] - b1) ** 2 + (hi[node, 2] - b2) ** 2)
        if _hull_distance(b0, b1, b2, c1, r1, c2, r2) > rb + margin:
            continue
        if child[node] >= 0:
            stack[top] = child[node]
            stack[top + 1] = child[node] + 1
            top += 2
            continue
        for i in range(start[node], start[node] + count[node]):
            behind = False
            for p in range(len(planes)):
                m = -np.inf
                for c in range(3):
                    m = max(m, planes[p, 0] * pieces[i, c, 0] + planes[p, 1] * pieces[i, c, 1]
                            + planes[p, 2] * pieces[i, c, 2])
                if m <= planes[p, 3]:
                    behind = True
                    break
            if behind:
                continue
            if _hull_distance(centre[i, 0], centre[i, 1], centre[i, 2], c1, r1, c2, r2) <= radius[i] + margin:
                return False
    return True


@nb.njit(cache=True)
def _face_flags(lo, hi, child, start, count, pieces, centre, radius, margin, fc, fr, fn, fv, lens_c, lens_r,
                face_plane_thr, has_mirror, mc, mn, lens_real):
    out = np.zeros(len(fc), np.uint8)
    use_face_plane = face_plane_thr > 0
    for f in range(len(fc)):
        n_pl = (1 if use_face_plane else 0) + (1 if has_mirror else 0)
        planes = np.empty((n_pl, 4))
        k = 0
        if use_face_plane:
            planes[k, :3] = fn[f]
            planes[k, 3] = fn[f, 0] * fv[f, 0] + fn[f, 1] * fv[f, 1] + fn[f, 2] * fv[f, 2] + face_plane_thr
            k += 1
        if has_mirror:
            planes[k, :3] = mn
            planes[k, 3] = mn[0] * mc[0] + mn[1] * mc[1] + mn[2] * mc[2] + margin
        if _clear(lo, hi, child, start, count, pieces, centre, radius, fc[f], fr[f], lens_c, lens_r, planes, margin):
            out[f] |= 1
        if has_mirror:
            # the mirror -> lens segments: reflections of the part of the first hull behind the mirror
            dist = (fc[f, 0] - mc[0]) * mn[0] + (fc[f, 1] - mc[1]) * mn[1] + (fc[f, 2] - mc[2]) * mn[2]
            rc = fc[f] - 2 * dist * mn
            if _clear(lo, hi, child, start, count, pieces, centre, radius, rc, fr[f], lens_real, lens_r,
                      planes[k:k + 1], margin):
                out[f] |= 2
    return out


def clear_faces(tree: OccluderTree, face_vertices_mm: np.ndarray, face_normals: np.ndarray, lens_center_mm,
                lens_radius_mm: float, ray_offset_mm: float, mirror=None) -> np.ndarray:
    """Per face (F,) uint8: bit 1 when every segment from the face (lifted by ``ray_offset_mm``)
    to the lens disk (centre ``lens_center_mm``, radius ``lens_radius_mm``; for a mirror view
    the virtual lens, and the segment ends at the mirror) meets no occluder; bit 2 (mirror
    views) when every mirror -> real lens segment is clear.  The face's own plane hides the
    triangles behind it only when the offset is well above the rounding margin."""
    tri = np.asarray(face_vertices_mm, np.float64)
    fc = tri.mean(axis=1)
    fr = np.linalg.norm(tri - fc[:, None], axis=2).max(axis=1) if len(tri) else np.zeros(0)
    thr = ray_offset_mm / 2 if ray_offset_mm >= 4 * tree.margin_mm else 0.0
    lens_c = np.asarray(lens_center_mm, np.float64)
    if mirror is not None:
        mc, mn = np.asarray(mirror.center_mm, float), np.asarray(mirror.normal, float)
        lens_real = mirror.reflect_points(lens_c[None])[0]
    else:
        mc = mn = lens_real = np.zeros(3)
    if tree.child.size == 0 or len(tree.pieces) == 0:
        return np.full(len(fc), 3 if mirror is not None else 1, np.uint8)
    return _face_flags(tree.lo, tree.hi, tree.child, tree.start, tree.count, tree.pieces, tree.centre, tree.radius,
                       tree.margin_mm, np.ascontiguousarray(fc), fr + tree.margin_mm,
                       np.ascontiguousarray(face_normals, np.float64), np.ascontiguousarray(tri[:, 0]), lens_c,
                       float(lens_radius_mm), thr, mirror is not None, mc, mn, lens_real)
