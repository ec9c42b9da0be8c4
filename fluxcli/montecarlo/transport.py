"""MCML-style photon transport (Wang, Jacques & Zheng 1995) in a homogeneous medium of
index ``n`` inside an analytic convex shape, in air.

Choices, and why:

- **Analogue absorption** (a photon is absorbed at an interaction with probability
  μa/μt, else scattered): every escaping photon carries weight exactly 1, so the images
  made from the photons are whole photons and their counts *are* the shot noise, and the
  truth per element is a count of real photons. Implicit capture would give fractional
  weights; at the albedos of tissue (μs/μt ≥ 0.9) analogue transport costs little more.
- **Probabilistic Fresnel** (reflect with probability R(θ), else refract out whole): each
  photon leaves at most once, with weight 1; weight splitting would again make fractions.
- Henyey–Greenstein phase function; ``g = 0`` samples cos θ = 2ξ − 1 exactly.
- Steps are drawn afresh after a reflection (the exponential is memoryless, so this is
  the same law as MCML's carried-over step).

Shapes, in the subject's own frame (centred at the origin): ``BOX`` with half sizes
(hx, hy, hz) (a slab is a box with very large hx, hy) and ``CYLINDER`` along x (radius,
half length), the orientation of :func:`fluxcli.surface.phantoms.cylinder`; or any closed
triangle mesh (:class:`fluxcli.montecarlo.meshbody.MeshBody`, kind ``MESH``), where the way out
of a step is found in a bounding-volume hierarchy and the exit's face is the triangle met.

Reproducibility: photons are split into a fixed number of streams (independent of the
thread count), each with its own xoroshiro128+ generator seeded by splitmix64 from
(seed, batch, stream); the same seed gives the same photons on any number of threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from .meshbody import MESH, STACK_DEPTH, MeshBody, mesh_hit

BOX, CYLINDER = 0, 1
N_STREAMS = 64  # photons of a batch are split into this many independent streams
MAX_EVENTS = 10_000_000  # a photon still inside after this many interactions is counted as lost

# exit codes per photon
ABSORBED, ESCAPED, LOST = 0, 1, 2
EVENTS_PER_S_PER_THREAD = 1.1e7  # interactions a second on one thread (2.2-2.5e7 measured on 2, box and cylinder)


def expected_events(medium: "Medium", half_mm) -> float:
    """About how many interactions a photon makes before it is absorbed or leaves a body whose
    smallest half size is ``min(half_mm)`` (mm): 1 / (μa/μt + 1 / (h² μt μt')), the mean number
    before analogue absorption (μt/μa) and a diffusive walk's to cross h (h² μt μt', μt' = μa +
    μs (1 - g)), whichever ends it first.  Within a factor 2 of the transport's own count on a
    30 x 40 x 20-mm box: μs 1, 10 and 100 /mm, μa 0.01 and 0 /mm (61, 964, 9.0e5 and 125
    measured; 51, 911, 1.0e6 and 102 here)."""
    mut = medium.mua_per_mm + medium.mus_per_mm
    mutr = medium.mua_per_mm + medium.mus_per_mm * (1.0 - medium.g)
    h = float(min(half_mm))
    escape = h * h * mut * mutr
    return 1.0 / (medium.mua_per_mm / mut + 1.0 / max(escape, 1.0))


@dataclass(frozen=True)
class Medium:
    """Optical properties: absorption and scattering coefficients (1/mm), HG anisotropy g,
    refractive index n (outside is air, n = 1)."""

    mua_per_mm: float
    mus_per_mm: float
    g: float
    refractive_index: float

    def __post_init__(self):
        if not (self.mua_per_mm >= 0 and self.mus_per_mm >= 0 and self.mua_per_mm + self.mus_per_mm > 0):
            raise ValueError("mua_per_mm and mus_per_mm must be >= 0 and not both 0")
        if not -1 < self.g < 1:
            raise ValueError("g must lie in (-1, 1)")
        if self.refractive_index < 1:
            raise ValueError("refractive_index must be >= 1")


@dataclass(frozen=True)
class Shape:
    """An analytic convex body centred at the origin: ``kind`` BOX (``half_mm`` = half sizes)
    or CYLINDER along x (``half_mm`` = (half length, radius, radius))."""

    kind: int
    half_mm: tuple[float, float, float]

    @classmethod
    def box(cls, size_mm) -> "Shape":
        s = [float(v) / 2 for v in size_mm]
        return cls(BOX, (s[0], s[1], s[2]))

    @classmethod
    def cylinder(cls, radius_mm: float, length_mm: float) -> "Shape":
        return cls(CYLINDER, (float(length_mm) / 2, float(radius_mm), float(radius_mm)))

    def contains(self, p_mm: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(p_mm)
        h = np.asarray(self.half_mm)
        if self.kind == BOX:
            return np.all(np.abs(p) < h, axis=1)
        return (np.abs(p[:, 0]) < h[0]) & (p[:, 1] ** 2 + p[:, 2] ** 2 < h[1] ** 2)

    def depth_mm(self, p_mm: np.ndarray) -> np.ndarray:
        """Distance from points to the nearest face (negative outside)."""
        p = np.atleast_2d(np.asarray(p_mm, float))
        h = np.asarray(self.half_mm)
        if self.kind == BOX:
            return np.min(h - np.abs(p), axis=1)
        return np.minimum(h[0] - np.abs(p[:, 0]), h[1] - np.hypot(p[:, 1], p[:, 2]))

    def outward_normals(self, p_mm: np.ndarray) -> np.ndarray:
        """Unit outward normal at points on the surface (the face the point is nearest to)."""
        p = np.atleast_2d(np.asarray(p_mm, float))
        h = np.asarray(self.half_mm)
        nrm = np.zeros_like(p)
        if self.kind == BOX:
            k = np.argmin(h - np.abs(p), axis=1)
            nrm[np.arange(len(p)), k] = np.sign(p[np.arange(len(p)), k])
            return nrm
        rho = np.hypot(p[:, 1], p[:, 2])
        cap = (h[0] - np.abs(p[:, 0])) < (h[1] - rho)
        nrm[cap, 0] = np.sign(p[cap, 0])
        side = ~cap
        nrm[side, 1] = p[side, 1] / rho[side]
        nrm[side, 2] = p[side, 2] / rho[side]
        return nrm

    def kernel_args(self) -> tuple:
        """The mesh arrays of the transport kernel: none for an analytic body."""
        return (np.zeros((0, 9)), np.zeros((0, 3)), np.zeros((0, 3)), *[np.zeros(0, np.int64)] * 5, np.zeros((0, 3)))


@dataclass
class Escaped:
    """Photons that left the body in one batch: exit points on the surface (mm, subject
    frame), directions in air (unit) and weights (photons; 1 each in analogue transport); for a
    mesh body also the triangle each left through (None for an analytic body)."""

    position_mm: np.ndarray
    direction: np.ndarray
    weight: np.ndarray
    face: np.ndarray | None = None


@dataclass
class Tally:
    """Bookkeeping over all batches (photons)."""

    launched: int = 0
    escaped: int = 0
    absorbed: int = 0
    lost: int = 0
    path_mm: float = 0.0  # total path length travelled inside (track-length estimator of absorption)


# ------------------------------------------------------------------ random numbers
@nb.njit(cache=True, inline="always")
def _splitmix64(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15))
    z = x
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x, z ^ (z >> np.uint64(31))


@nb.njit(cache=True, inline="always")
def _rotl(x, k):
    return (x << np.uint64(k)) | (x >> np.uint64(64 - k))


@nb.njit(cache=True, inline="always")
def _next(state):
    """xoroshiro128+: a uniform number in (0, 1) (never 0: it feeds a logarithm)."""
    s0 = state[0]
    s1 = state[1]
    result = s0 + s1
    s1 ^= s0
    state[0] = _rotl(s0, 24) ^ s1 ^ (s1 << np.uint64(16))
    state[1] = _rotl(s1, 37)
    return ((result >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740993.0)


# ------------------------------------------------------------------ geometry
@nb.njit(cache=True, inline="always")
def _slab(h, p, u, low_face, best, face):
    """The nearer of (best, face) and the exit through the slab |p| <= h along u: face
    ``low_face`` at -h, ``low_face + 1`` at +h."""
    if u > 0:
        t = (h - p) / u
        if t < best:
            return t, low_face + 1
    elif u < 0:
        t = (-h - p) / u
        if t < best:
            return t, low_face
    return best, face


@nb.njit(cache=True, inline="always")
def _distance_out(kind, h0, h1, h2, x, y, z, ux, uy, uz):
    """Distance along (ux, uy, uz) from an inside point to the boundary, and the face hit
    (0..5 box faces -x,+x,-y,+y,-z,+z; cylinder 0/1 caps, 2 side)."""
    best = 1e300
    face = -1
    if kind == BOX:
        best, face = _slab(h0, x, ux, 0, best, face)
        best, face = _slab(h1, y, uy, 2, best, face)
        best, face = _slab(h2, z, uz, 4, best, face)
    else:
        if ux > 0:
            best, face = (h0 - x) / ux, 1
        elif ux < 0:
            best, face = (-h0 - x) / ux, 0
        a = uy * uy + uz * uz
        if a > 0:
            b = y * uy + z * uz
            c = y * y + z * z - h1 * h1
            disc = b * b - a * c
            if disc < 0:
                disc = 0.0
            t = (-b + math.sqrt(disc)) / a  # the larger root: the way out of a convex body
            if t < 0:
                t = 0.0
            if t < best:
                best, face = t, 2
    if best < 0:
        best = 0.0
    return best, face


@nb.njit(cache=True, inline="always")
def _normal(kind, face, y, z, h1):
    if kind == BOX:
        nx = ny = nz = 0.0
        s = 1.0 if face % 2 == 1 else -1.0
        if face < 2:
            nx = s
        elif face < 4:
            ny = s
        else:
            nz = s
        return nx, ny, nz
    if face == 0:
        return -1.0, 0.0, 0.0
    if face == 1:
        return 1.0, 0.0, 0.0
    r = math.sqrt(y * y + z * z)
    return 0.0, y / r, z / r


@nb.njit(cache=True, inline="always")
def fresnel_reflectance(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance from medium n1 into n2 at incidence cos_i (≥ 0);
    1 beyond the critical angle. Also returns cos of the refracted angle."""
    if n1 == n2:
        return 0.0, cos_i
    sin_i = math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
    sin_t = n1 / n2 * sin_i
    if sin_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    if cos_i > 1.0 - 1e-12:
        r = (n1 - n2) / (n1 + n2)
        return r * r, cos_t
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (rs * rs + rp * rp), cos_t


@nb.njit(cache=True, inline="always")
def _scatter(state, g, ux, uy, uz):
    """New direction after a Henyey–Greenstein scattering (MCML's rotation)."""
    xi = _next(state)
    if g == 0.0:
        ct = 2.0 * xi - 1.0
    else:
        tmp = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
        ct = (1.0 + g * g - tmp * tmp) / (2.0 * g)
        ct = min(1.0, max(-1.0, ct))
    st = math.sqrt(max(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * _next(state)
    cp = math.cos(phi)
    sp = math.sin(phi)
    if abs(uz) > 0.99999:
        return st * cp, st * sp, ct * (1.0 if uz > 0 else -1.0)
    tmp = math.sqrt(1.0 - uz * uz)
    nx = st * (ux * uz * cp - uy * sp) / tmp + ux * ct
    ny = st * (uy * uz * cp + ux * sp) / tmp + uy * ct
    nz = -st * cp * tmp + uz * ct
    norm = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * norm, ny * norm, nz * norm


@nb.njit(cache=True, parallel=True)
def _transport(seed, batch, n_photons, kind, half, mua, mus, g, n_in, src, src_radius, beam,
               tri, bmin, bmax, left, right, start, count, order, tri_normal,
               out_pos, out_dir, out_code, out_face, path_per_stream):
    mut = mua + mus
    albedo = mus / mut
    h0, h1, h2 = half[0], half[1], half[2]
    per = (n_photons + N_STREAMS - 1) // N_STREAMS
    for s in nb.prange(N_STREAMS):
        state = np.empty(2, np.uint64)
        x0 = np.uint64(seed) * np.uint64(0x100000001B3) ^ (np.uint64(batch) << np.uint64(20)) ^ np.uint64(s)
        x0, state[0] = _splitmix64(x0)
        x0, state[1] = _splitmix64(x0)
        path = 0.0
        stack = np.empty(STACK_DEPTH, np.int64)
        for i in range(s * per, min(n_photons, (s + 1) * per)):
            # launch: isotropic, from a point or uniformly in a small ball
            x, y, z = src[0], src[1], src[2]
            if src_radius > 0:
                while True:
                    a = 2 * _next(state) - 1
                    b = 2 * _next(state) - 1
                    c = 2 * _next(state) - 1
                    if a * a + b * b + c * c <= 1:
                        break
                x += src_radius * a
                y += src_radius * b
                z += src_radius * c
            if beam[0] == 0.0 and beam[1] == 0.0 and beam[2] == 0.0:
                uz = 2.0 * _next(state) - 1.0
                st = math.sqrt(max(0.0, 1.0 - uz * uz))
                phi = 2.0 * math.pi * _next(state)
                ux = st * math.cos(phi)
                uy = st * math.sin(phi)
            else:
                ux, uy, uz = beam[0], beam[1], beam[2]
            code = LOST
            skip = -1  # the mesh triangle the photon was just turned back from
            for _ in range(MAX_EVENTS):
                step = -math.log(_next(state)) / mut
                if kind == MESH:
                    dist, face = mesh_hit(x, y, z, ux, uy, uz, step, skip, tri, bmin, bmax, left, right, start,
                                          count, order, stack)
                    if face < 0:
                        dist = 1e300
                else:
                    dist, face = _distance_out(kind, h0, h1, h2, x, y, z, ux, uy, uz)
                if step < dist:
                    x += step * ux
                    y += step * uy
                    z += step * uz
                    path += step
                    skip = -1
                    if _next(state) > albedo:
                        code = ABSORBED
                        break
                    ux, uy, uz = _scatter(state, g, ux, uy, uz)
                    continue
                # reach the boundary
                x += dist * ux
                y += dist * uy
                z += dist * uz
                path += dist
                if kind == MESH:
                    nx, ny, nz = tri_normal[face, 0], tri_normal[face, 1], tri_normal[face, 2]
                else:
                    nx, ny, nz = _normal(kind, face, y, z, h1)
                # put the point exactly on the face it reached (no drift out of the body); on a mesh
                # the hit lies on its triangle to rounding, and the next query passes that triangle over
                if kind == MESH:
                    pass
                elif kind == BOX:
                    if face < 2:
                        x = nx * h0
                    elif face < 4:
                        y = ny * h1
                    else:
                        z = nz * h2
                else:
                    if face == 2:
                        y, z = ny * h1, nz * h1
                    else:
                        x = nx * h0
                cos_i = ux * nx + uy * ny + uz * nz
                if kind == MESH and cos_i < -1e-6:  # met a face from outside: slipped through a crack
                    break
                if cos_i <= 0.0:  # grazing rounding: it is not leaving; turn it back in
                    cos_i = 0.0
                r, cos_t = fresnel_reflectance(cos_i, n_in, 1.0)
                if r >= 1.0 or _next(state) <= r:
                    ux -= 2 * cos_i * nx
                    uy -= 2 * cos_i * ny
                    uz -= 2 * cos_i * nz
                    skip = face
                    continue
                # refract into air (Snell, vector form): t = n u + (cos_t - n cos_i) N
                k = cos_t - n_in * cos_i
                tx = n_in * ux + k * nx
                ty = n_in * uy + k * ny
                tz = n_in * uz + k * nz
                norm = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
                out_pos[i, 0], out_pos[i, 1], out_pos[i, 2] = x, y, z
                out_dir[i, 0], out_dir[i, 1], out_dir[i, 2] = tx * norm, ty * norm, tz * norm
                out_face[i] = face
                code = ESCAPED
                break
            out_code[i] = code
        path_per_stream[s] = path


def transport(medium: Medium, shape: "Shape | MeshBody", source_mm, n_photons: int, *, seed: int = 0, batch: int = 0,
              source_radius_mm: float = 0.0, beam_direction=None, tally: Tally | None = None) -> Escaped:
    """Transport ``n_photons`` photons launched isotropically at ``source_mm`` (subject frame,
    inside the body), or all along ``beam_direction`` (a unit vector: a pencil beam, as in
    MCML's validation); returns the escaped ones. ``batch`` numbers independent batches of the
    same seed; ``tally`` (updated in place) counts launched, escaped, absorbed and lost
    photons and the total path length."""
    src = np.asarray(source_mm, float)
    if shape.depth_mm(src[None])[0] <= source_radius_mm:
        raise ValueError(f"the source {src.tolist()} mm is not inside the body")
    n = int(n_photons)
    beam = np.zeros(3) if beam_direction is None else np.asarray(beam_direction, float) / np.linalg.norm(beam_direction)
    pos = np.zeros((n, 3))
    dirs = np.zeros((n, 3))
    code = np.full(n, LOST, np.int8)
    face = np.full(n, -1, np.int64)
    path = np.zeros(N_STREAMS)
    _transport(np.uint64(seed), np.uint64(batch), n, shape.kind, np.asarray(shape.half_mm, float),
               float(medium.mua_per_mm), float(medium.mus_per_mm), float(medium.g), float(medium.refractive_index),
               src, float(source_radius_mm), beam, *shape.kernel_args(), pos, dirs, code, face, path)
    esc = code == ESCAPED
    if tally is not None:
        tally.launched += n
        tally.escaped += int(esc.sum())
        tally.absorbed += int((code == ABSORBED).sum())
        tally.lost += int((code == LOST).sum())
        tally.path_mm += float(path.sum())
    return Escaped(pos[esc], dirs[esc], np.ones(int(esc.sum())), face[esc] if shape.kind == MESH else None)
