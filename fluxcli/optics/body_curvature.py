"""The body's own curvature in the ``diffuse`` emission profile (``subject.emission.body_curvature``).

The depth term (:func:`fluxcli.optics.emission.depth_term`) takes the surface as flat: the
radiance leaving along s_i is the scattering source integrated back along the ray,
``int phi(z(s)) e^{-s/l} ds / l``, with the diffusion field of a flat boundary,
``phi'' = mu_eff^2 phi`` and ``phi'(0) = phi(0) / z_b``, and the ray's depth ``z = s mu'``.
Under a body that curves (mean curvature H, > 0 where convex) both change:

- the diffusion equation in coordinates along the normal reads ``phi'' = mu_eff^2 phi +
  2 H(z) phi' - lap_t phi`` (the divergence of the normals, 2H, grows with depth as ``H / (1 - H z)``
  under a sphere), so the fluence grows faster with depth under a convex surface;
- the ray behind an oblique exit runs under a surface that falls away from it: its depth is
  ``s mu' - H s^2 (1 - mu'^2) / 2 + ...`` (exactly, under a sphere of radius 1/H,
  ``(2 s mu' - H s^2) / (1 + sqrt(1 - 2 H s mu' + H^2 s^2))``).

The first makes the light that comes from deep, along the normal, brighter; the second makes the
grazing light, which comes from shallow, dimmer. Both steepen the profile of a convex body
(a sphere of radius 12 mm, mu_s' 1 /mm: ~4 % more light along the normal, ~3 % less at 70-80 deg)
and flatten that of a concave one. To first order in H the ray integral gains
``H l^2 (3 mu'^2 - 1) / z_b``, but under a sphere of 12 mm that is less than half of what the
sphere's exact field (and the photons) give, so the table here integrates the field itself: ``phi`` from the normal ODE with
the sphere's ``H(z)`` (the osculating sphere of the body's mean curvature), then the ray integral
along the sphere's depth, for each H on a grid. The ratio to the flat integral, normalised so
that it carries no light of its own (an element's power is its exitance times its area), is
the factor this module applies per element and view at the angle to the view's lens centre, as
the curvature term does (:func:`fluxcli.transfer_cache.curvature_ratios`): T's columns stay power
fractions. The direction-dependent part (k_n - H, for a body curved more one way than the
other: a cylinder) is left out; on a cylinder of 12.5 mm the photons' light at 65-80 deg is then
0.2-0.7 % above the factor's (benchmarks/body_curvature_photons.py).

The tangential-flux term (:func:`fluxcli.optics.emission.tangent_length`) weighs the exitance's
gradient by how far along the surface the ray behind an exit reaches: ``s sin(theta')`` under a
flat surface, the arc to the foot of the ray's point under the osculating sphere, where the
fluence it meets also grows faster.  Its ray weight takes that sideways moment over the flat one
(:func:`tangent_factor_table`, the same share taken out); under a sphere of 12 mm the photons
drift 1.5x / 1.2x as far as over a slab at 20-40 / 40-65 deg, the factor says 1.43x / 1.26x.

Checked against photons (tests/test_body_curvature.py; benchmarks/body_curvature_photons.py for
24 mm and the cylinder): fluxcli's Monte Carlo from the centre of a sphere of radius 12 mm (mu_s
1 /mm, mu_a 0.01 /mm, n 1.40), the exit angles in bands: the flat profile is off by up to +3.7 /
-3.5 %, the profile with this factor within the photons' noise (0.5 %). A limit: the field it
integrates is the osculating sphere's, a fluence that varies with depth alone, which is the field
of a deep, central source.  Over a source 5-6 mm under the skin the light 4-20 mm from its foot
leaves as a slab's does (the cylinder and the ellipsoid, region by region: the factor is 1-3 % too
steep there, and right over the whole side only on average; benchmarks/ellipsoid_photons.py
--bands). H of a mesh comes from the turn of its normals over a few transport lengths
(:func:`mean_curvature`): 0 on a box's faces, 1/2R on a cylinder's side, 1/R on a sphere.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

LAYOUT = "osculating-sphere-2"  # what a T cache key records when the factor is on (bump when the table changes)
HL_MAX = 0.2  # |H| l at most (a sphere of 5 transport lengths' radius): the field's expansion beyond is not the body's
N_H = 41  # the table's H grid: H l = -HL_MAX ... HL_MAX
N_MU = 129  # and its grid in the cosine outside, mu = k / (N_MU - 1)
MAX_NEIGHBOURS = 200  # more elements than this in the fitting disc: gathered into cells first (mean_curvature)
SAME_PLANE_COS = 0.8  # neighbours whose normals turn more than ~37 deg are another face (a box's edge), not curvature


def _fields(h: np.ndarray, c: float, zb: float, z: np.ndarray) -> np.ndarray:
    """phi(z) / phi(0) under spheres of curvature ``h`` (1/l; < 0 concave), lengths in l:
    (len(h), len(z)), the normal ODE ``phi'' = c phi + 2 h / (1 - h z) phi'`` from ``phi(0) = 1``,
    ``phi'(0) = 1/zb`` (classic RK4 on the uniform ``z``).  Under a convex body the ODE is
    followed to depth 0.6 / h only (nearer the centre its singular term is a point source's,
    not the body's) and held flat beyond."""
    h = np.asarray(h, float)
    dz = z[1] - z[0]
    stop = np.where(h > 0, 0.6 / np.where(h > 0, h, 1.0), np.inf)

    def rhs(zz, y, yp):
        on = zz < stop
        k = np.where(on, 2.0 * h / np.where(on, 1.0 - h * zz, 1.0), 0.0)
        return np.where(on, yp, 0.0), np.where(on, c * y + k * yp, 0.0)

    out = np.empty((len(h), len(z)))
    y, yp = np.ones(len(h)), np.full(len(h), 1.0 / zb)
    for i, zz in enumerate(z):
        out[:, i] = y
        a1, b1 = rhs(zz, y, yp)
        a2, b2 = rhs(zz + dz / 2, y + dz / 2 * a1, yp + dz / 2 * b1)
        a3, b3 = rhs(zz + dz / 2, y + dz / 2 * a2, yp + dz / 2 * b2)
        a4, b4 = rhs(zz + dz, y + dz * a3, yp + dz * b3)
        y, yp = y + dz / 6 * (a1 + 2 * a2 + 2 * a3 + a4), yp + dz / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
    return out


def ray_integrals(h_grid: np.ndarray, mu_inside: np.ndarray, c: float, zb: float,
                  moment: bool = False) -> np.ndarray:
    """``int phi(z(s)) e^{-s} ds`` (lengths in l) for each curvature of ``h_grid`` (1/l) and
    inside cosine of ``mu_inside``: (len(h_grid), len(mu_inside)).  The ray leaves a convex body
    where its depth turns negative (the chord's end); nothing is counted beyond.  With
    ``moment``: ``int x(s) phi(z(s)) e^{-s} ds / sin(theta')`` instead, x the arc length along the
    surface from the exit point to the foot (on the sphere's radius) of the ray's point at s: the
    sideways reach of the ray that the tangential-flux term weighs the exitance's gradient by
    (``s sin(theta')`` under a flat surface)."""
    s = np.linspace(0.0, 40.0, 4001)
    z = np.linspace(0.0, 40.0, 4001)
    w = np.exp(-s) * (s[1] - s[0])
    w[0] *= 0.5
    phis = _fields(np.asarray(h_grid, float), c, zb, z)
    out = np.empty((len(h_grid), len(mu_inside)))
    m = np.asarray(mu_inside, float)[:, None]
    st = np.sqrt(np.maximum(1.0 - m * m, 1e-12))
    for i, h in enumerate(np.asarray(h_grid, float)):
        root = np.sqrt(np.maximum(1.0 - 2.0 * h * s * m + h * h * s * s, 0.0))
        depth = (2.0 * s * m - h * s * s) / (1.0 + root)
        inside = depth >= 0 if h > 0 else np.ones_like(depth, bool)
        if h > 0:  # past the chord's end (s > 2 mu' / h) the ray is outside
            inside &= s <= 2.0 * m / h
        val = np.where(inside, np.interp(np.clip(depth, 0.0, 40.0), z, phis[i]), 0.0)
        if moment:  # the foot's arc length over sin(theta'): s under a flat surface
            val = val * (s if h == 0 else np.arctan2(abs(h) * s * st, 1.0 - h * s * m) / (abs(h) * st))
        out[i] = np.sum(val * w, axis=1)
    return out


@lru_cache(maxsize=16)
def _ratios(n: float, depth_c: float, moment: bool = False) -> np.ndarray:
    """The ray integral (or its sideways moment) under each curvature of the grid over the flat
    one, (N_H, N_MU)."""
    from .emission import boundary_A

    zb = 2.0 * boundary_A(n) / 3.0  # in units of l
    mu = np.linspace(0.0, 1.0, N_MU)
    mu_in = np.sqrt(1.0 - (1.0 - mu * mu) / n**2)
    L = ray_integrals(np.linspace(-HL_MAX, HL_MAX, N_H), mu_in, depth_c, zb, moment)
    flat = ray_integrals(np.array([0.0]), mu_in, depth_c, zb, moment)[0]
    out = L / flat
    out.flags.writeable = False
    return out


def _shares(n: float, depth_c: float, weight_table: np.ndarray) -> np.ndarray:
    from .emission import _moment, interp_weight

    w = interp_weight(np.asarray(weight_table, float), np.linspace(0.0, 1.0, N_MU))
    return np.array([_moment(w * r) for r in _ratios(float(n), float(depth_c))]) / _moment(w)


def factor_table(n: float, depth_c: float, weight_table: np.ndarray) -> np.ndarray:
    """The factor (N_H, N_MU) by which the body's mean curvature multiplies the profile's ray
    weight, on the grids ``H l = linspace(-HL_MAX, HL_MAX, N_H)`` and ``mu = linspace(0, 1,
    N_MU)`` (cosine outside); each row carries no light of its own against ``weight_table`` (the
    profile's ``pi p`` on its own cos grid): ``int w f mu dmu = int w mu dmu``."""
    ratio = _ratios(float(n), float(depth_c))
    return np.ascontiguousarray(ratio / _shares(n, depth_c, weight_table)[:, None])


def tangent_factor_table(n: float, depth_c: float, weight_table: np.ndarray) -> np.ndarray:
    """The factor (N_H, N_MU, the grids of :func:`factor_table`) by which the body's mean
    curvature multiplies the tangential-flux term's ray weight ``pi p g``: the sideways moment of
    the ray integral under the curved surface over the flat one, with the same share taken out as
    for the scalar part (M is the light that leaves).  Under a convex body it is larger: the ray
    reaches further along the surface at depth, where the fluence is larger too (a sphere of 12 mm:
    the photons' drift 1.2-1.6x a flat slab's at 20-65 deg)."""
    ratio = _ratios(float(n), float(depth_c), True)
    return np.ascontiguousarray(ratio / _shares(n, depth_c, weight_table)[:, None])


def factor(table: np.ndarray, cos_theta: np.ndarray, H_per_mm: np.ndarray, transport_per_mm: float) -> np.ndarray:
    """The table's factor (bilinear) at ``cos_theta`` (outside) and mean curvature ``H_per_mm``
    (1/mm), with ``|H| l`` clipped to :data:`HL_MAX`; 1 behind the surface."""
    mu = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    hl = np.clip(np.asarray(H_per_mm, float) / float(transport_per_mm), -HL_MAX, HL_MAX)
    x = (hl + HL_MAX) / (2 * HL_MAX) * (N_H - 1)
    y = mu * (N_MU - 1)
    i = np.clip(np.floor(x).astype(np.int64), 0, N_H - 2)
    j = np.clip(np.floor(y).astype(np.int64), 0, N_MU - 2)
    fx, fy = x - i, y - j
    t = table
    val = ((1 - fx) * (1 - fy) * t[i, j] + fx * (1 - fy) * t[i + 1, j]
           + (1 - fx) * fy * t[i, j + 1] + fx * fy * t[i + 1, j + 1])
    return np.where(np.asarray(cos_theta, float) > 0, val, 1.0)


def mean_curvature(surface, radius_mm: float) -> np.ndarray:
    """The mean curvature H (1/mm, > 0 convex) at each element of ``surface``: the symmetric
    2 x 2 shape operator S that best turns the in-plane offsets ``d`` of the element centroids
    within ``radius_mm`` into the in-plane turn of their normals, ``n_g - n_e ~ S d``
    (least squares, weighted by area), and ``H = trace(S) / 2``.  Neighbours whose normals turn
    by more than ~37 deg (:data:`SAME_PLANE_COS`) are another face, not curvature: a box's faces
    get 0 up to their edges.  A faceted body's flat facets are averaged over (the radius should
    span a facet or two).  An element with too few neighbours in its plane gets 0.

    Elements much smaller than the radius (more than :data:`MAX_NEIGHBOURS` in its disc) are first gathered into cells of a quarter of it (by
    the side their normal faces most, so that a box's faces never share one): the fit is made
    on the cells' area-weighted centroids and normals, and each element takes its cell's H.  A
    mesh of 80 000 elements then takes a second, not minutes, and nothing is lost: the fit
    reads the normals' turn over the whole radius either way."""
    from .emission import element_geometry

    S, cen, nrm = element_geometry(surface)
    E = surface.n_elements
    H = np.zeros(E)
    idx = np.flatnonzero(S > 0)
    if len(idx) < 2:
        return H
    if np.pi * radius_mm**2 / np.median(S[idx]) <= MAX_NEIGHBOURS:  # elements as they are
        H[idx] = _fit_shape(S[idx], cen[idx], nrm[idx], float(radius_mm))
        return H
    axis = np.argmax(np.abs(nrm[idx]), axis=1)
    side = 2 * axis + (nrm[idx, axis] > 0)
    cell = np.floor((cen[idx] - cen[idx].min(axis=0)) / (radius_mm / 4.0)).astype(np.int64)
    _, cid = np.unique(np.column_stack([cell, side]), axis=0, return_inverse=True)
    cid = cid.ravel()
    n_c = int(cid.max()) + 1
    Sc = np.bincount(cid, S[idx], n_c)
    cen_c = np.stack([np.bincount(cid, S[idx] * cen[idx, k], n_c) for k in range(3)], axis=1) / Sc[:, None]
    nrm_c = np.stack([np.bincount(cid, S[idx] * nrm[idx, k], n_c) for k in range(3)], axis=1)
    ln = np.linalg.norm(nrm_c, axis=1)[:, None]
    nrm_c = np.divide(nrm_c, ln, out=np.zeros_like(nrm_c), where=ln > 0)
    H[idx] = _fit_shape(Sc, cen_c, nrm_c, float(radius_mm))[cid]
    return H


def _fit_shape(S: np.ndarray, cen: np.ndarray, nrm: np.ndarray, radius_mm: float) -> np.ndarray:
    """H at each point (area ``S``, centroid ``cen``, unit normal ``nrm``) from its neighbours
    within ``radius_mm`` that face the same way (:func:`mean_curvature`)."""
    from scipy.spatial import cKDTree

    E = len(S)
    pairs = cKDTree(cen).query_pairs(radius_mm, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(E)
    pf = np.concatenate([pairs[:, 0], pairs[:, 1]])
    pg = np.concatenate([pairs[:, 1], pairs[:, 0]])
    keep = np.einsum("ij,ij->i", nrm[pf], nrm[pg]) >= SAME_PLANE_COS
    pf, pg = pf[keep], pg[keep]
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(nrm, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-300)[:, None]
    e2 = np.cross(nrm, e1)
    dc, dn = cen[pg] - cen[pf], nrm[pg] - nrm[pf]
    d1, d2 = np.einsum("ij,ij->i", e1[pf], dc), np.einsum("ij,ij->i", e2[pf], dc)
    t1, t2 = np.einsum("ij,ij->i", e1[pf], dn), np.einsum("ij,ij->i", e2[pf], dn)
    w = S[pg]

    def acc(x):  # least squares for (a, b, c) of S = [[a, b], [b, c]]: t1 = a d1 + b d2, t2 = b d1 + c d2
        return np.bincount(pf, w * x, E)

    q11, q22, q12 = acc(d1 * d1), acc(d2 * d2), acc(d1 * d2)
    N = np.zeros((E, 3, 3))
    N[:, 0, 0], N[:, 0, 1], N[:, 1, 0] = q11, q12, q12
    N[:, 1, 1], N[:, 1, 2], N[:, 2, 1], N[:, 2, 2] = q11 + q22, q12, q12, q22
    rhs = np.stack([acc(d1 * t1), acc(d2 * t1 + d1 * t2), acc(d2 * t2)], axis=1)
    ev = np.linalg.eigvalsh(N)
    ok = (np.bincount(pf, minlength=E) >= 3) & (ev[:, 0] > 1e-6 * np.maximum(ev[:, -1], 1e-300)) & (ev[:, -1] > 0)
    H = np.zeros(E)
    if ok.any():
        sol = np.linalg.solve(N[ok], rhs[ok][..., None])[..., 0]
        H[ok] = 0.5 * (sol[:, 0] + sol[:, 2])
    return H


def fit_radius_mm(surface, transport_per_mm: float) -> float:
    """The neighbourhood :func:`mean_curvature` reads a body's curvature over: three transport
    lengths (the depth the light that leaves comes from), and at least twice an element's
    typical size (so that a faceted body's neighbouring facets are in it)."""
    from .emission import element_geometry

    S, _, _ = element_geometry(surface)
    size = float(np.sqrt(np.median(S[S > 0]))) if np.any(S > 0) else 0.0
    return max(3.0 / float(transport_per_mm), 2.0 * size)


def view_factors(surface, views, emission, tangential: bool = False) -> list[np.ndarray]:
    """Per view, per element of ``surface`` (placed) the body-curvature factor of ``emission``
    at the angle from the element's normal to the view's lens centre (a mirror view's virtual
    one) and the element's mean curvature (:func:`mean_curvature`); with ``tangential`` the
    factor of its tangential-flux term (:func:`tangent_factor_table`)."""
    from .emission import element_geometry

    transport = emission.reduced_scattering_per_mm + emission.absorption_per_mm
    H = mean_curvature(surface, fit_radius_mm(surface, transport))
    _, cen, nrm = element_geometry(surface)
    table = emission.body_tangent if tangential else emission.body
    out = []
    for v in views:
        d = np.asarray(v.camera.center_mm, float) - cen
        cos = np.einsum("ij,ij->i", nrm, d) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        out.append(factor(table, cos, H, transport))
    return out
