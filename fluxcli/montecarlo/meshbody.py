"""A closed triangle mesh as the body photons travel through: the subject's own surface (a mesh
file, a captured surface) when ``simulate.flux.kind: montecarlo`` is not given an analytic box
or cylinder.

- **Where a step leaves the body.** A bounding-volume hierarchy over the triangles (median
  split along the longest axis of the centroids, four triangles a leaf), walked per step with
  the step's own length as the far limit, so a step deep inside visits few boxes; the nearest
  triangle the step crosses is found by Möller–Trumbore in double precision, from either
  side (a ray from inside meets the faces' backs).
- **The triangle just left is passed over** on the next query (a reflected photon starts on
  it), so rounding cannot make a photon meet its own face again at a distance of 0.
- **A face met from outside** (the outward normal and the direction more than 1e-6 apart in
  the wrong sense) means the photon slipped through a crack between triangles in rounding:
  it is counted as lost, never followed outside. The tally says how many; on the meshes tried
  none was.
- **Light that leaves is not followed back in.** A photon that leaves a concave body may
  head for another part of it (between a mouse's legs); the truth counts it where it left,
  as exitance is defined, and the camera's occlusion test stops it, as the body would.

The hierarchy is built by numba in O(m log² m) for m triangles (~1 s for 3 × 10⁵).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

MESH = 2  # shape kind beside transport.BOX and transport.CYLINDER
LEAF_TRIANGLES = 4
STACK_DEPTH = 128  # nodes pending in one walk; a median split of 10^8 triangles is 25 deep


@nb.njit(cache=True)
def _build_bvh(cent, lo, hi, leaf):
    m = cent.shape[0]
    order = np.arange(m)
    cap = max(1, 2 * m)
    bmin = np.empty((cap, 3))
    bmax = np.empty((cap, 3))
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    s_node = np.empty(STACK_DEPTH, np.int64)
    s_lo = np.empty(STACK_DEPTH, np.int64)
    s_hi = np.empty(STACK_DEPTH, np.int64)
    s_node[0], s_lo[0], s_hi[0] = 0, 0, m
    sp = 1
    n_nodes = 1
    while sp > 0:
        sp -= 1
        node, a, b = s_node[sp], s_lo[sp], s_hi[sp]
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for k in range(3):
            bmin[node, k] = np.inf
            bmax[node, k] = -np.inf
        for i in range(a, b):
            j = order[i]
            for k in range(3):
                bmin[node, k] = min(bmin[node, k], lo[j, k])
                bmax[node, k] = max(bmax[node, k], hi[j, k])
                cmin[k] = min(cmin[k], cent[j, k])
                cmax[k] = max(cmax[k], cent[j, k])
        axis = 0
        for k in range(1, 3):
            if cmax[k] - cmin[k] > cmax[axis] - cmin[axis]:
                axis = k
        if b - a <= leaf or cmax[axis] - cmin[axis] <= 0.0 or sp + 2 > STACK_DEPTH:
            start[node], count[node] = a, b - a
            continue
        sub = order[a:b].copy()
        idx = np.argsort(cent[sub, axis])
        for i in range(b - a):
            order[a + i] = sub[idx[i]]
        mid = (a + b) // 2
        left[node], right[node] = n_nodes, n_nodes + 1
        s_node[sp], s_lo[sp], s_hi[sp] = n_nodes, a, mid
        s_node[sp + 1], s_lo[sp + 1], s_hi[sp + 1] = n_nodes + 1, mid, b
        sp += 2
        n_nodes += 2
    return bmin[:n_nodes].copy(), bmax[:n_nodes].copy(), left[:n_nodes].copy(), right[:n_nodes].copy(), \
        start[:n_nodes].copy(), count[:n_nodes].copy(), order


@nb.njit(cache=True)
def mesh_hit(ox, oy, oz, dx, dy, dz, tmax, skip, tri, bmin, bmax, left, right, start, count, order, stack):
    """The nearest triangle the ray o + t d, 0 < t <= tmax, crosses (either side), leaving out
    triangle ``skip``: (t, triangle), or (tmax, -1) if none. ``tri`` rows: v0, e1, e2 (9 floats);
    ``stack``: scratch of STACK_DEPTH ints."""
    ix = 1.0 / dx if dx != 0.0 else math.copysign(1e300, dx)
    iy = 1.0 / dy if dy != 0.0 else math.copysign(1e300, dy)
    iz = 1.0 / dz if dz != 0.0 else math.copysign(1e300, dz)
    best = tmax
    face = -1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        n = stack[sp]
        t0 = (bmin[n, 0] - ox) * ix
        t1 = (bmax[n, 0] - ox) * ix
        tn, tf = min(t0, t1), max(t0, t1)
        t0 = (bmin[n, 1] - oy) * iy
        t1 = (bmax[n, 1] - oy) * iy
        tn, tf = max(tn, min(t0, t1)), min(tf, max(t0, t1))
        t0 = (bmin[n, 2] - oz) * iz
        t1 = (bmax[n, 2] - oz) * iz
        tn, tf = max(tn, min(t0, t1)), min(tf, max(t0, t1))
        if tf < 0.0 or tn > tf or tn > best:
            continue
        if left[n] < 0:
            for k in range(start[n], start[n] + count[n]):
                j = order[k]
                if j == skip:
                    continue
                e1x, e1y, e1z = tri[j, 3], tri[j, 4], tri[j, 5]
                e2x, e2y, e2z = tri[j, 6], tri[j, 7], tri[j, 8]
                px = dy * e2z - dz * e2y
                py = dz * e2x - dx * e2z
                pz = dx * e2y - dy * e2x
                det = e1x * px + e1y * py + e1z * pz
                if det == 0.0:
                    continue
                inv = 1.0 / det
                sx, sy, sz = ox - tri[j, 0], oy - tri[j, 1], oz - tri[j, 2]
                u = (sx * px + sy * py + sz * pz) * inv
                if u < 0.0 or u > 1.0:
                    continue
                qx = sy * e1z - sz * e1y
                qy = sz * e1x - sx * e1z
                qz = sx * e1y - sy * e1x
                v = (dx * qx + dy * qy + dz * qz) * inv
                if v < 0.0 or u + v > 1.0:
                    continue
                t = (e2x * qx + e2y * qy + e2z * qz) * inv
                if 0.0 < t <= best:
                    best, face = t, j
        elif sp + 2 <= stack.shape[0]:
            stack[sp] = left[n]
            stack[sp + 1] = right[n]
            sp += 2
    return best, face


class MeshBody:
    """A closed, outward-wound triangle mesh (mm, the subject's own frame) that photons travel
    through. Build it with :meth:`of`, which refuses a surface that does not enclose a volume."""

    kind = MESH

    def __init__(self, vertices_mm: np.ndarray, faces: np.ndarray):
        v = np.asarray(vertices_mm, np.float64)
        f = np.asarray(faces, np.int64)
        t = v[f]
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        n = np.cross(e1, e2)
        self.vertices_mm, self.faces = v, f
        self.normals = n / np.linalg.norm(n, axis=1)[:, None]
        self.tri = np.ascontiguousarray(np.concatenate([t[:, 0], e1, e2], axis=1))
        self.bvh = _build_bvh(t.mean(axis=1), t.min(axis=1), t.max(axis=1), LEAF_TRIANGLES)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.half_mm = tuple(float(x) for x in (hi - lo) / 2)

    @classmethod
    def of(cls, vertices_mm, faces, name: str = "subject.surface") -> "MeshBody":
        """The body a closed surface encloses; ValueError naming ``name`` if it is not closed."""
        from ..surface.mesh import edge_face_counts

        counts = edge_face_counts(faces)
        if len(faces) < 4 or np.any(counts != 2):
            holes, more = int(np.count_nonzero(counts == 1)), int(np.count_nonzero(counts > 2))
            raise ValueError(f"{name} is not a closed surface ({holes} edge(s) belong to one face only, "
                             f"{more} to more than two), so it encloses no body for photons to travel through. A "
                             "captured or scanned surface is usually open underneath: close it (a watertight mesh "
                             "of the whole subject), or use an analytic phantom (box or cylinder)")
        t = np.asarray(vertices_mm, float)[np.asarray(faces)]
        volume = float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)
        if not volume > 0:
            raise ValueError(f"{name} encloses no volume ({volume:.3g} mm^3 with its faces wound as they are)")
        return cls(vertices_mm, faces)

    def kernel_args(self) -> tuple:
        return (self.tri, *self.bvh[:6], self.bvh[6], self.normals)

    def first_hit(self, origin: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance and triangle where rays (n, 3) first meet the surface (inf, -1 where none)."""
        o, d = np.atleast_2d(origin).astype(float), np.atleast_2d(direction).astype(float)
        return _first_hits(o, d / np.linalg.norm(d, axis=1)[:, None], self.tri, *self.bvh)

    def contains(self, p_mm: np.ndarray) -> np.ndarray:
        """Inside the body: the first face met along three fixed directions is met from inside
        (its outward normal along the ray) by at least two of them."""
        p = np.atleast_2d(np.asarray(p_mm, float))
        votes = np.zeros(len(p), int)
        for d in ((0.5773, 0.5774, 0.5774), (-0.2673, 0.5345, -0.8018), (0.8, -0.6, 0.0)):
            dirs = np.tile(np.asarray(d) / np.linalg.norm(d), (len(p), 1))
            t, face = self.first_hit(p, dirs)
            ok = face >= 0
            votes[ok] += np.einsum("ij,ij->i", self.normals[face[ok]], dirs[ok]) > 0
        return votes >= 2

    def depth_mm(self, p_mm: np.ndarray) -> np.ndarray:
        """Distance from points to the surface, negative outside."""
        p = np.atleast_2d(np.asarray(p_mm, float))
        t = self.vertices_mm[self.faces]
        dist = np.array([np.sqrt(_point_triangle_d2(q, t).min()) for q in p])
        return np.where(self.contains(p), dist, -dist)

    def outward_normals(self, p_mm: np.ndarray, face: np.ndarray | None = None) -> np.ndarray:
        """The outward normal of the face each point left through (``face``, from the transport)
        or, without it, of the nearest face."""
        if face is None:
            t = self.vertices_mm[self.faces]
            face = np.array([int(np.argmin(_point_triangle_d2(q, t))) for q in np.atleast_2d(p_mm)])
        return self.normals[np.asarray(face)]


@nb.njit(cache=True, parallel=True)
def _first_hits(o, d, tri, bmin, bmax, left, right, start, count, order):
    n = o.shape[0]
    t_out = np.full(n, np.inf)
    f_out = np.full(n, -1, np.int64)
    for i in nb.prange(n):
        stack = np.empty(STACK_DEPTH, np.int64)
        t, f = mesh_hit(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], 1e300, -1, tri, bmin, bmax, left,
                        right, start, count, order, stack)
        if f >= 0:
            t_out[i], f_out[i] = t, f
    return t_out, f_out


def _point_triangle_d2(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Squared distance from point p (3,) to each triangle of t (m, 3, 3): the closest point by
    regions (Ericson, Real-Time Collision Detection §5.1.5), vectorised."""
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        q = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        wab = d1 / (d1 - d3)
        q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * wab[:, None], q)
        wac = d2 / (d2 - d6)
        q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * wac[:, None], q)
        wbc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        q = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + (c - b) * wbc[:, None], q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    return np.einsum("ij,ij->i", p - q, p - q)
