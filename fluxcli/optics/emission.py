"""How light leaves the surface: the angular emission profile p(theta) of the forward model.

Radiance leaving a surface point is ``L(r, theta) = M(r) p(theta)`` (M the exitance), with p
normalised so that ``integral of p(theta) cos(theta) dOmega = 1`` over the outer hemisphere
(Lambertian: p = 1/pi).  An element's power is then unchanged, and a column of T stays the
fraction of the element's power that reaches each pixel; every ray of the T estimators is
weighted by ``pi p(theta_s)`` (:meth:`Profile.weight`), theta_s the angle at the real surface
between its outward normal and the ray leaving it.

Profiles (docs/design.md, "Emission"):

``lambertian``
    p = 1/pi, ray weight 1 (the estimators keep their old arithmetic: T to the bit).
``diffuse(n)``
    a turbid medium of refractive index n behind a smooth surface, into air: the diffusion-theory
    radiance at the boundary inside, ``L_in(mu') ~ phi/4pi + 3 J mu'/4pi`` with the Robin
    (partial-current) boundary ``J = phi / 2A``, A from the exact partial-current integrals of the
    unpolarised Fresnel reflectance (Haskell et al. 1994), carried out through the surface by
    Fresnel transmission at the internal angle theta' (sin theta = n sin theta') and the n^2
    change of radiance; then normalised.
    Given the medium (on by default), the fluence's curvature with depth: the diffusion equation
    makes phi'' = mu_eff^2 phi under a flat, slowly varying exitance, so the deeper light that
    leaves along the normal is brighter, by the factor ``1 + c mu'^2``, c = 3 mu_a / mu_t'
    (:func:`depth_term`; docs/design.md, "Emission: the depth term"). Nothing for a clear
    medium; 3 % for a phantom (mu_a 0.01, mu_s' 1 /mm); 30 % and more for tissue in the visible.
    With it (on by default) the tangential flux of the same diffusion field: where the
    exitance varies along the surface the light leaves tilted away from where it is
    brighter, ``L_t(r, s) = -p(theta) g(theta) grad_t M . s`` with
    ``g = (1 + 3 mu' / A) / (n mu_t' (1 + 3 mu' / 2A))`` (mm), mu_t' = mu_a + mu_s'; see
    :func:`tangent_length` and docs/design.md, "Emission: the tangential flux".
    With it (on by default) the body's own curvature: under a convex surface the fluence grows
    faster with depth and oblique rays run under a surface that falls away, so each element's
    profile is bent by its mean curvature (:mod:`fluxcli.optics.body_curvature`; 1 on flat faces).
``table``
    a measured or computed curve (angle from the normal in degrees, or cos theta) -> relative
    radiance, interpolated linearly and normalised.

Arrays and numbers only: no config, no files, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

N_TABLE = 4097  # ray weights are tabulated on mu = cos(theta) = k / (N_TABLE - 1), linear in between
CHECK_DEG = (30.0, 45.0, 60.0, 70.0, 75.0, 80.0)  # where reports and notices quote the curve
# Beyond this angle from the normal an element's value is not known from a diffuse surface's
# light: every view that collects it sees it at cos(theta) < 0.17, where a 1-degree error in the
# normal moves the light it sends by 10 % or more, the tangential-flux term (first order in
# grad ln M, ~sin(theta)) is at its largest, and the profile has been checked point by point
# against Monte Carlo photons only up to 80 deg (docs/design.md; face-averaged, the photons' exit
# angles follow diffuse(1.40) within 1 % in every band to 90 deg).  On the Monte Carlo box turned
# edge-on to a close lens (-90 deg) such elements read 2-3x their truth and carried 86-95 % of the
# "observed" total.  An element whose light the views collect only beyond this angle is solved
# for (its light stays its own) but is not counted as observed
# (fluxcli.inverse.diagnostics.leave_out_edge_on).  Applied to ``diffuse`` only: Lambertian and
# table profiles keep their results (the Lambertian battery's figures are unchanged).
DIFFUSE_TRUSTED_TO_DEG = 80.0
KAPPA_L2_MAX = 0.5  # the curvature term: |lap_t M / M| l^2 at most this (it is first order in it)
TANGENT_LAYOUT = "face-frame-2"  # how T_tangent is stored (2 in-plane components per face): in its cache key


# ------------------------------------------------------------------ Fresnel and the boundary
def fresnel_reflectance(cos_inside: np.ndarray, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of light inside a medium of index ``n`` meeting its
    boundary with air at the angle whose cosine is ``cos_inside`` (1 beyond the critical angle)."""
    ci = np.clip(np.asarray(cos_inside, float), 0.0, 1.0)
    if n == 1.0:  # no interface (even at grazing incidence)
        return np.zeros_like(ci)
    st = n * np.sqrt(np.maximum(1.0 - ci * ci, 0.0))  # sine of the refracted angle, in air
    out = np.ones_like(ci)
    ok = st < 1.0
    ct = np.sqrt(1.0 - st[ok] ** 2)
    c = ci[ok]
    rs = (n * c - ct) / (n * c + ct)
    rp = (n * ct - c) / (n * ct + c)
    out[ok] = 0.5 * (rs * rs + rp * rp)
    return out


def _gauss_legendre(a: float, b: float, m: int = 200) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(m)
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


def boundary_A(n: float) -> float:
    """The Robin boundary coefficient A of diffusion theory (``phi = 2 A J_n`` at the surface)
    from the exact partial-current integrals of the Fresnel reflectance (Haskell et al. 1994,
    JOSA A 11:2727, eqs. 2.9-2.13): ``R_phi = int_0^1 2 mu R(mu) dmu``, ``R_J = int_0^1 3 mu^2
    R(mu) dmu``, ``R_eff = (R_phi + R_J) / (2 - R_phi + R_J)``, ``A = (1 + R_eff) / (1 - R_eff)``.
    R jumps to 1 at the critical angle, so each side of it is integrated by Gauss-Legendre
    (exact to ~1e-12).  A = 1 for n = 1."""
    if not n >= 1.0:
        raise ValueError(f"refractive index must be >= 1, got {n}")
    if n == 1.0:
        return 1.0
    mu_c = np.sqrt(1.0 - 1.0 / n**2)  # cosine of the critical angle
    r_phi = r_j = 0.0
    for a, b in ((0.0, mu_c), (mu_c, 1.0)):
        x, w = _gauss_legendre(a, b)
        r = fresnel_reflectance(x, n)
        r_phi += float(np.sum(w * 2 * x * r))
        r_j += float(np.sum(w * 3 * x * x * r))
    r_eff = (r_phi + r_j) / (2 - r_phi + r_j)
    return (1 + r_eff) / (1 - r_eff)


def diffuse_radiance(cos_theta: np.ndarray, n: float, depth: float = 0.0, anisotropy: float = 0.0) -> np.ndarray:
    """Radiance leaving a diffusive medium of index ``n`` into air at the angle whose cosine is
    ``cos_theta`` (outside), unnormalised: ``T_F(theta') (1 + 3 mu' / 2A) (1 + depth mu'^2)``
    with ``cos theta' = mu' = sqrt(1 - sin^2 theta / n^2)`` and ``depth`` the depth term's
    coefficient (:func:`depth_term`; 0: P1's profile); the constant factors (phi/4pi, 1/n^2)
    drop out when normalised.

    ``anisotropy`` (the phase function's g; 0: isotropic scattering) shortens the depth term as
    the δ-Eddington ray integral says (:func:`delta_eddington_g`, docs/design.md): its z² part by
    (1 − g*) and its z³ part by (1 − g*)², so the factor is ``(1 + 3 mu'/2A) + depth mu'^2
    (1 − g*) (1 + (1 − g*) 3 mu'/2A)`` (the same as above for g = 0)."""
    mu = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    mu_in = np.sqrt(1.0 - (1.0 - mu * mu) / n**2)
    a = 3.0 * mu_in / (2.0 * boundary_A(n))
    q = 1.0 - delta_eddington_g(anisotropy)
    return (1.0 - fresnel_reflectance(mu_in, n)) * ((1.0 + a) + depth * mu_in * mu_in * q * (1.0 + q * a))


def delta_eddington_g(anisotropy: float) -> float:
    """The anisotropy ``g* = g / (1 + g)`` of the δ-Eddington phase function (Joseph, Wiscombe &
    Weinman 1976, J. Atmos. Sci. 33, 2452) that stands for a forward-peaked one of anisotropy g:
    a share f = g² of the scattering goes straight on (a ray that keeps its direction, as if
    unscattered), the rest scatters with the first moment g*, so μ_s (1 − f)(1 − g*) = μ_s (1 − g)
    keeps μ_s′.  In the ray integral behind the exit radiance (docs/design.md) the straight-on
    part only thins the attenuation; what is left scatters at μ_s* = μ_s′ / (1 − g*), a shorter
    path than 1/μ_s′ when g > 0.  0 for isotropic scattering."""
    g = float(anisotropy)
    if not (np.isfinite(g) and 0.0 <= g < 1.0):
        raise ValueError(f"scattering_anisotropy must be a number in [0, 1), got {anisotropy}")
    return g / (1.0 + g)


def depth_term(reduced_scattering_per_mm: float, absorption_per_mm: float) -> float:
    """The coefficient ``c = (mu_eff l)^2 = 3 mu_a / (mu_a + mu_s')`` of the depth term
    ``1 + c mu'^2`` of the diffuse profile.

    Derivation (docs/design.md, "Emission: the depth term"): the radiance leaving along s_i is
    the scattering source integrated back along the ray, ``int phi(z) e^{-z / l mu'} dz / l mu'``
    (l = 1 / mu_t', z depth).  Under a surface whose exitance varies slowly along it, the
    diffusion equation gives ``phi'' = mu_eff^2 phi`` (mu_eff^2 = 3 mu_a mu_t'), and the Robin
    boundary ``phi'(0) = phi(0) / z_b`` (z_b = 2 A l / 3), so ``phi = phi(0) (1 + z / z_b +
    mu_eff^2 z^2 / 2 + mu_eff^2 z^3 / 6 z_b + ...)``; the ray integral is then
    ``phi(0) (1 + 3 mu' / 2A) (1 + (mu_eff l)^2 mu'^2)`` to first order in mu_eff^2 (all orders
    in l / z_b).  Where the exitance curves along the surface the curvature adds to mu_eff^2
    locally; averaged over a face it adds nothing (the integral of a Laplacian), which is why the
    term is a property of the medium.  Checked against fluxcli's photon Monte Carlo
    (tests/test_emission.py; docs/design.md has the table): at n 1.40 and mu_a 0.01-0.3 /mm it
    takes the profile's worst band to 80 deg from up to 13 % off to within 3 % (n 1: 15 % -> 4.4 %).
    That is for isotropic scattering (mu_s reduced to mu_s' by similarity); with forward-peaked
    scattering of the same mu_s' (g 0.5-0.9) the photons want 0-0.85 of c, less at low mu_a
    (docs/design.md, "Tissue's scattering").  Told the medium's g, :func:`diffuse_radiance`
    shortens it as the δ-Eddington ray integral says (about half of c at g 0.9)."""
    mus, mua = float(reduced_scattering_per_mm), float(absorption_per_mm)
    return 3.0 * mua / (mua + mus)


# ------------------------------------------------------------------ the profile
@dataclass(frozen=True, eq=False)  # eq would compare arrays
class Profile:
    """An emission profile: ray weights ``pi p`` tabulated on mu = cos(theta) in [0, 1].

    ``table`` is empty for ``lambertian`` (weight 1 exactly: the estimators skip the
    multiplication); else (N_TABLE,) float64, ``table[k] = pi p(mu_k)``, mu_k = k/(N_TABLE-1),
    normalised so that ``2 int_0^1 weight(mu) mu dmu = 1`` (the trapezoid rule on the table's
    own linear interpolant: the estimators integrate exactly that function).
    """

    model: str
    table: np.ndarray = field(repr=False)
    refractive_index: float | None = None
    source: str | None = None  # a table's file name, for reports
    # the tangential-flux term (diffuse only): pi p(theta) g(theta) on the same mu grid, mm; empty: off
    tangent: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    reduced_scattering_per_mm: float | None = None
    absorption_per_mm: float | None = None
    depth_term: float = 0.0  # diffuse: the coefficient c of the depth term 1 + c mu'^2 in the table (0: none)
    scattering_anisotropy: float = 0.0  # diffuse: the medium's g (the depth and tangential terms' δ-Eddington g*)
    # the curvature term (diffuse only): l^2 h(theta) / p(theta) on the same mu grid, mm^2; empty: off
    curvature: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    # the body's own curvature (diffuse only): T's columns scaled per element and view by the factor of
    # :mod:`fluxcli.optics.body_curvature` at the element's mean curvature and emission angle (False: off)
    body_curvature: bool = False

    @property
    def body(self) -> np.ndarray:
        """The body-curvature factor table (N_H, N_MU) of :func:`fluxcli.optics.body_curvature.factor_table`."""
        from .body_curvature import factor_table

        return factor_table(self.refractive_index, self.depth_term, self.table)

    @property
    def body_tangent(self) -> np.ndarray:
        """The body-curvature factor table of the tangential-flux term
        (:func:`fluxcli.optics.body_curvature.tangent_factor_table`)."""
        from .body_curvature import tangent_factor_table

        return tangent_factor_table(self.refractive_index, self.depth_term, self.table)

    @property
    def has_tangent(self) -> bool:
        return len(self.tangent) > 0

    def tangent_weight(self, cos_theta) -> np.ndarray:
        """``pi p(theta) g(theta)`` (mm) at ``cos_theta``: a ray's tangential weight per unit
        of ``-grad_t M / M . s_o`` (0 behind the surface, or when the term is off)."""
        mu = np.asarray(cos_theta, float)
        if not self.has_tangent:
            return np.zeros_like(mu)
        return np.where(mu > 0, interp_weight(self.tangent, np.clip(mu, 0.0, 1.0)), 0.0)

    @property
    def has_curvature(self) -> bool:
        return len(self.curvature) > 0

    def curvature_ratio(self, cos_theta) -> np.ndarray:
        """``l^2 h(theta) / p(theta)`` (mm^2) at ``cos_theta``: the light the curvature term sends
        along theta per unit of ``lap_t M``, over the light the profile sends per unit of M (0
        behind the surface, or when the term is off; :func:`curvature_ratio`)."""
        mu = np.asarray(cos_theta, float)
        if not self.has_curvature:
            return np.zeros_like(mu)
        return np.where(mu > 0, interp_weight(self.curvature, np.clip(mu, 0.0, 1.0)), 0.0)

    @property
    def is_lambertian(self) -> bool:
        return len(self.table) == 0

    @property
    def trusted_to_deg(self) -> float:
        """The angle from the normal up to which the profile is known (90: everywhere); see
        :data:`DIFFUSE_TRUSTED_TO_DEG`."""
        return DIFFUSE_TRUSTED_TO_DEG if self.model == "diffuse" else 90.0

    def weight(self, cos_theta) -> np.ndarray:
        """The ray weight ``pi p(theta)`` at ``cos_theta`` (0 for cos <= 0, behind the surface)."""
        mu = np.asarray(cos_theta, float)
        if self.is_lambertian:
            return np.where(mu > 0, 1.0, 0.0)
        return np.where(mu > 0, interp_weight(self.table, np.clip(mu, 0.0, 1.0)), 0.0)

    def radiance(self, theta_rad) -> np.ndarray:
        """Radiance relative to its value along the normal, L(theta)/L(0)."""
        return self.weight(np.cos(np.asarray(theta_rad, float))) / float(self.weight(1.0))

    def p(self, cos_theta) -> np.ndarray:
        """p(theta) itself (1/sr): ``weight / pi``."""
        return self.weight(cos_theta) / np.pi

    def key(self) -> dict | None:
        """What the T cache key and the geometry digest record: None for Lambertian (their keys
        are then what they were before emission profiles existed), else the model and the
        SHA-256 of the weight table (a table file is keyed by its numbers, not its path)."""
        if self.is_lambertian:
            return None
        import hashlib

        out = {"model": self.model, "weights_sha256": hashlib.sha256(self.table.tobytes()).hexdigest()}
        if self.refractive_index is not None:
            out["refractive_index"] = float(self.refractive_index)
        if self.depth_term:  # absent when off: the key of a diffuse T before the term existed
            out["depth_term"] = round(float(self.depth_term), 9)  # as artefacts store numbers (store.canonical)
        if self.scattering_anisotropy and (self.depth_term or self.has_tangent):  # absent for g 0 (as before)
            out["scattering_anisotropy"] = round(float(self.scattering_anisotropy), 9)
        if self.has_tangent:  # absent when off: the key of a diffuse T before the term existed
            out["tangent_sha256"] = hashlib.sha256(self.tangent.tobytes()).hexdigest()
            out["tangent_layout"] = TANGENT_LAYOUT
        if self.has_curvature:  # absent when off: the key of a diffuse T before the term existed
            out["curvature_sha256"] = hashlib.sha256(self.curvature.tobytes()).hexdigest()
        if self.body_curvature:  # absent when off: the key of a diffuse T before the term existed
            from .body_curvature import LAYOUT

            out["body_curvature"] = LAYOUT
            out["transport_per_mm"] = round(float(self.reduced_scattering_per_mm + self.absorption_per_mm), 9)
        return out

    def describe(self) -> str:
        if self.model == "diffuse":
            terms = [t for t, on in ((f"its depth term (c {self.depth_term:.3g})", self.depth_term),
                                     ("its tangential flux", self.has_tangent),
                                     ("its curvature term", self.has_curvature),
                                     ("the body's curvature", self.body_curvature)) if on]
            if terms:
                g = (f", g {self.scattering_anisotropy:g}" if self.scattering_anisotropy
                     and (self.depth_term or self.has_tangent) else "")
                return (f"diffuse (refractive index {self.refractive_index:g}) with {' and '.join(terms)} "
                        f"(mu_s' {self.reduced_scattering_per_mm:g} /mm, mu_a {self.absorption_per_mm:g} /mm{g})")
            return f"diffuse (refractive index {self.refractive_index:g})"
        if self.model == "table":
            return f"table ({self.source})" if self.source else "table"
        return "lambertian"


def interp_weight(table: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Linear interpolation of a weight table at mu in [0, 1], the same arithmetic the numba
    kernel uses (:func:`fluxcli.optics.transfer_kernel.emission_weight`)."""
    n = len(table)
    t = np.asarray(mu, float) * (n - 1)
    i = np.minimum(t.astype(np.int64), n - 2)
    f = t - i
    return table[i] + (table[i + 1] - table[i]) * f


def _normalised(values: np.ndarray) -> np.ndarray:
    """Scale a non-negative curve on the mu grid so that ``2 int_0^1 f(mu) mu dmu = 1`` for its
    linear interpolant (exact: per interval, int of a linear f times mu)."""
    mu = np.linspace(0.0, 1.0, len(values))
    h = mu[1] - mu[0]
    a, b = values[:-1], values[1:]
    m0, m1 = mu[:-1], mu[1:]
    # int over [m0, m1] of (a (m1 - x) + b (x - m0)) / h * x dx
    integral = np.sum(h * (a * (2 * m0 + m1) + b * (m0 + 2 * m1)) / 6.0)
    if not integral > 0:
        raise ValueError("the profile emits nothing (zero everywhere)")
    return np.ascontiguousarray(values / (2.0 * integral))


def lambertian() -> Profile:
    return Profile("lambertian", np.zeros(0))


# The tangential term's default medium: a reduced scattering coefficient of ~1 /mm is the
# order of soft tissue and of tissue phantoms in the red / near infrared (Jacques 2013, Phys.
# Med. Biol. 58 R37: mu_s' ~ 0.5-2 /mm for most soft tissues at 600-800 nm), and 0.01 /mm
# absorption that of a phantom (it enters only through mu_t' = mu_a + mu_s').
DEFAULT_REDUCED_SCATTERING_PER_MM = 1.0
DEFAULT_ABSORPTION_PER_MM = 0.01


def tangent_length(cos_theta: np.ndarray, n: float, transport_per_mm: float, anisotropy: float = 0.0) -> np.ndarray:
    """The length ``g(theta)`` (mm) that turns the relative exitance gradient into the
    tangential part of the radiance leaving the surface: outside,
    ``L = M p(theta) (1 - g(theta) grad_t M / M . s_o)``, with

        g = (l / n) (1 + 3 mu' / A) / (1 + 3 mu' / 2A),   l = 1 / mu_t',

    mu' the cosine inside (Snell), A the Robin coefficient (:func:`boundary_A`).

    Derivation (docs/design.md, "Emission: the tangential flux"): the radiance reaching the
    surface from inside along s_i is the scattering source ``mu_s phi / 4pi`` integrated back
    along the ray, ``int phi(r - s s_i) e^{-mu_t s} mu_s ds / 4pi``, with the half-space
    diffusion field near the surface ``phi = (z + z_b) m(x)`` (z depth, z_b = 2 A D the
    extrapolation length, D = l / 3).  Its normal part is P1's ``phi/4pi (1 + 3 mu' / 2A)``
    (the profile p); its tangential part, ``-(l / 4pi) (z_b + 2 mu' l) s_i,t . grad m``, holds
    the tangential gradient at the depth the light comes from, which grows as (z + z_b): P1's
    ``3 J_t . s_i / 4pi`` (J_t = -D grad_t phi at the surface) is the z_b term alone, short by
    the factor (1 + 3 mu' / A) (about 2 at n 1.40, 3.5 at n 1).  Through the surface
    ``s_i,t = s_o,t / n`` (Snell) and grad m / m = grad M / M (M proportional to phi(0)).
    Checked against the photons of fluxcli.montecarlo (tests/test_emission.py): the drift of
    the exit directions away from the source matches this g within a few per cent at n 1.00
    and 1.40, where P1's is a factor 2-3.5 short.

    ``anisotropy`` g: forward-peaked scattering of the same mu_s'.  With the δ-Eddington phase
    function (:func:`delta_eddington_g`) the source along the ray is ``mu_s* (phi + 3 g* J . s_i)
    / 4pi`` over the path ``e^{-mu_s* s}``, mu_s* = mu_s' / (1 − g*).  The normal part is P1's
    again (similarity).  The tangential part gathers the field's tangential gradient from
    ``phi`` over the shorter path, ``(1 − g*)(z_b + 2 mu' l (1 − g*))``, and from ``J``: its
    tangential component, ``g* (z_b + mu' l (1 − g*))``, and its normal one, which also varies
    along the ray's sideways walk, ``g* (1 − g*) mu' l``.  Together ``z_b + 2 mu' l (1 − g*)``: the
    light comes from nearer the surface, where the tangential gradient is smaller, so

        g = (l / n) (1 + 3 mu' (1 − g*) / A) / (1 + 3 mu' / 2A),

    the same as above for g 0.  At n 1.40 and 40-65°: 0.92 mm (g 0), 0.78 (g 0.5), 0.72 (g 0.9);
    beyond 5 mm from the source the photons of a slab drift ~0.91, ~0.78 and ~0.72 mm
    (benchmarks/drift_rings.py; docs/design.md).  P1's own phase moment in place of the
    δ-Eddington one (g* = g) would give 0.54 mm at g 0.9: the forward peak does not turn the light
    it scatters."""
    mu = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    mu_in = np.sqrt(1.0 - (1.0 - mu * mu) / n**2)
    A = boundary_A(n)
    gs = delta_eddington_g(anisotropy)
    return (1.0 + 3.0 * mu_in * (1.0 - gs) / A) / (n * transport_per_mm * (1.0 + 3.0 * mu_in / (2.0 * A)))


def _moment(values: np.ndarray) -> float:
    """``int_0^1 f(mu) mu dmu`` of the linear interpolant of ``values`` on the mu grid (exact)."""
    mu = np.linspace(0.0, 1.0, len(values))
    h = mu[1] - mu[0]
    a, b, m0, m1 = values[:-1], values[1:], mu[:-1], mu[1:]
    return float(np.sum(h * (a * (2 * m0 + m1) + b * (m0 + 2 * m1)) / 6.0))


def curvature_ratio(cos_theta: np.ndarray, n: float, depth: float, transport_per_mm: float,
                    anisotropy: float = 0.0) -> np.ndarray:
    """``l^2 h(theta) / p(theta)`` (mm^2): where the exitance curves along the surface
    (``lap_t M``, 1/mm^2 times M) the light leaving at theta is ``M p (1 + this x lap_t M / M)``.

    Derivation (docs/design.md, "Emission: the curvature term"): the depth term's ray integral
    with the diffusion equation in full, ``phi'' = mu_eff^2 phi - lap_t phi``, and with the
    tangential walk of the ray back into the medium (depth z, sideways z tan theta'), whose
    second-order part averaged over azimuth is ``(z tan theta')^2 lap_t phi / 4``.  To first
    order in ``kappa = lap_t phi / phi`` (= lap_t M / M at the surface):

        L_in(mu') / phi(0) ~ (1 + 3 mu'/2A)(1 + c mu'^2)
                             + kappa l^2 [(1 - mu'^2)(1 + 9 mu'/2A) / 2 - mu'^2 (1 + 3 mu'/2A)],

    l = 1 / mu_t'.  The second line carries flux of its own; M is the light that leaves, so its
    share of the profile is taken out (``h`` carries none: ``int h cos dOmega = 0``) and the term
    moves light between angles: for kappa < 0 (over a buried source) more along the normal and
    less at grazing angles, for kappa > 0 (far from it) the reverse.  Fresnel's transmission is
    common to both lines and cancels in the ratio.  Checked against photons (tests/test_emission.py)."""
    mu = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    A = boundary_A(n)

    def ratio(m):
        mi = np.sqrt(1.0 - (1.0 - m * m) / n**2)
        p_in = (1.0 + 1.5 * mi / A) * (1.0 + depth * mi * mi)
        h_in = 0.5 * (1.0 - mi * mi) * (1.0 + 4.5 * mi / A) - mi * mi * (1.0 + 1.5 * mi / A)
        return h_in / p_in

    grid = np.linspace(0.0, 1.0, N_TABLE)
    p_grid = diffuse_radiance(grid, n, depth, anisotropy)  # the flux each part carries, by the tables' own rule
    share = _moment(p_grid * ratio(grid)) / _moment(p_grid)
    return (ratio(mu) - share) / transport_per_mm**2


def diffuse(refractive_index: float = 1.40, *, tangential: bool = False, depth: bool = False,
            curvature: bool = False, body: bool = False, reduced_scattering_per_mm: float = DEFAULT_REDUCED_SCATTERING_PER_MM,
            absorption_per_mm: float = DEFAULT_ABSORPTION_PER_MM, scattering_anisotropy: float = 0.0) -> Profile:
    """The diffusion-theory profile (P1 with a Fresnel boundary); with ``depth`` the depth term
    of a medium with these coefficients (:func:`depth_term`), with ``tangential`` its
    tangential-flux term (:func:`tangent_length`), with ``curvature`` its curvature term
    (:func:`curvature_ratio`), with ``body`` the body's own curvature
    (:mod:`fluxcli.optics.body_curvature`).  None: the coefficients are not used.
    ``scattering_anisotropy``: the medium's g, which shortens the depth and tangential terms
    (:func:`delta_eddington_g`); the curvature and body terms keep their isotropic derivation."""
    n = float(refractive_index)
    if not (np.isfinite(n) and n >= 1.0):
        raise ValueError(f"refractive index must be a number >= 1, got {refractive_index}")
    mus, mua = float(reduced_scattering_per_mm), float(absorption_per_mm)
    if tangential or depth or curvature or body:
        if not (np.isfinite(mus) and mus > 0):
            raise ValueError(f"reduced_scattering_per_mm must be a number > 0, got {reduced_scattering_per_mm}")
        if not (np.isfinite(mua) and mua >= 0):
            raise ValueError(f"absorption_per_mm must be a number >= 0, got {absorption_per_mm}")
    g = float(scattering_anisotropy)
    delta_eddington_g(g)  # checks it
    c = depth_term(mus, mua) if depth else 0.0
    mu = np.linspace(0.0, 1.0, N_TABLE)
    table = _normalised(diffuse_radiance(mu, n, c, g))
    if not (tangential or depth or curvature or body):
        return Profile("diffuse", table, refractive_index=n)
    tangent = np.ascontiguousarray(table * tangent_length(mu, n, mus + mua, g)) if tangential else np.zeros(0)
    curv = np.ascontiguousarray(curvature_ratio(mu, n, c, mus + mua, g)) if curvature else np.zeros(0)
    return Profile("diffuse", table, refractive_index=n, tangent=tangent, reduced_scattering_per_mm=mus,
                   absorption_per_mm=mua, depth_term=c, curvature=curv, body_curvature=bool(body),
                   scattering_anisotropy=g)


def table(x, radiance, *, unit: str = "deg", source: str | None = None) -> Profile:
    """A tabulated profile: ``x`` angles from the normal in degrees (``unit="deg"``) or cos theta
    (``unit="cos"``), ``radiance`` relative radiance (any scale).  Linear in the given variable
    between points, constant beyond the first and last.  ValueError says what is wrong."""
    x = np.asarray(x, float)
    r = np.asarray(radiance, float)
    if x.ndim != 1 or r.shape != x.shape or len(x) < 2:
        raise ValueError("needs at least two rows of (angle, radiance)")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
        raise ValueError("holds a value that is not a finite number")
    if np.any(r < 0):
        raise ValueError(f"holds a negative radiance ({r.min():g})")
    if unit == "deg":
        if x.min() < 0 or x.max() > 90:
            raise ValueError(f"angles must lie in 0..90 degrees from the normal (got {x.min():g}..{x.max():g})")
        if not (np.all(np.diff(x) > 0) or np.all(np.diff(x) < 0)):
            raise ValueError("angles must increase (or decrease) strictly from row to row")
        order = np.argsort(x)
        x, r = x[order], r[order]
    elif unit == "cos":
        if x.min() < 0 or x.max() > 1:
            raise ValueError(f"cos theta must lie in 0..1 (got {x.min():g}..{x.max():g})")
        if not (np.all(np.diff(x) > 0) or np.all(np.diff(x) < 0)):
            raise ValueError("cos theta must be strictly monotone from row to row")
        order = np.argsort(x)
        x, r = x[order], r[order]
    else:
        raise ValueError(f"unit must be 'deg' or 'cos', got {unit!r}")
    if not r.max() > 0:
        raise ValueError("the profile emits nothing (zero everywhere)")
    r = r / r.max()  # any scale: 1e-320 or 1e308 as well as 1
    mu = np.linspace(0.0, 1.0, N_TABLE)
    if unit == "deg":  # linear in the angle, as given
        vals = np.interp(np.degrees(np.arccos(mu)), x, r)
    else:
        vals = np.interp(mu, x, r)
    if not vals[-1] > 0:
        raise ValueError("the radiance along the normal (0 degrees) must be > 0")
    return Profile("table", _normalised(vals), source=source)


def table_from_csv(text: str, source: str | None = None) -> Profile:
    """A tabulated profile from the text of a CSV: one row per angle, the first column the angle
    from the normal, the second the relative radiance (more columns are ignored; lines starting
    with # are skipped).  The first column is in degrees unless its header names a cosine
    (``cos_theta``, ``mu``) or radians (``theta_rad``); a header is optional (``angle_deg`` as
    in the docs, or any of ``theta``, ``angle``, ``deg``); without one the column is read as
    cos theta when every value lies in 0..1, else as degrees.  Commas, semicolons (then a decimal
    comma is read too), tabs or spaces separate the columns; a spreadsheet's byte-order mark is
    skipped.  ValueError says what is wrong (the caller names the file)."""
    lines = [ln for ln in text.removeprefix("\ufeff").splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError("is empty")
    first = lines[0]
    sep = "," if "," in first and ";" not in first else ";" if ";" in first else "\t" if "\t" in first else None
    rows = [[c.strip().strip('"').strip() for c in (ln.split(sep) if sep else ln.split())] for ln in lines]
    if sep == ";":  # a spreadsheet in a decimal-comma locale
        rows = [[c.replace(",", ".") for c in row] for row in rows]
    header, body = (None, rows) if _numbers(rows[0][:2]) else (rows[0], rows[1:])
    how = ""
    if header is None:
        unit = None
    else:
        head = header[0].lower()
        if len(header) < 2:
            raise ValueError(f"has one column ({header[0]!r}); two are needed: the angle and the radiance "
                             "(a header row like 'angle_deg,radiance' or 'cos_theta,radiance')")
        if "cos" in head or head in ("mu", "cos"):
            unit = "cos"
        elif "rad" in head.replace("radiance", "") and "deg" not in head:
            unit = "rad"
        elif any(k in head for k in ("deg", "theta", "angle")):
            unit = "deg"
        else:
            raise ValueError(f"its first column's header {header[0]!r} names neither an angle (angle_deg, theta_deg, "
                             "theta_rad) nor a cosine (cos_theta); write 'angle_deg,radiance' or 'cos_theta,radiance'")
    x, r = [], []
    for k, row in enumerate(body, start=2 if header is not None else 1):
        if len(row) < 2:
            raise ValueError(f"row {k} has {len(row)} column(s); two are needed")
        try:
            x.append(float(row[0]))
            r.append(float(row[1]))
        except ValueError:
            raise ValueError(f"row {k} holds {row[0]!r}, {row[1]!r}, which are not both numbers") from None
    if unit is None:  # no header: a cosine if every value could be one, else degrees
        unit = "cos" if len(x) and 0 <= min(x) and max(x) <= 1 else "deg"
        how = f" (no header: the first column read as {'cos theta' if unit == 'cos' else 'degrees'})"
    if unit == "rad":  # pi/2 written to 12 digits is 90 degrees, not a hair past it
        x, unit = list(np.clip(np.degrees(x), None, 90.0) if max(x) <= np.pi / 2 + 1e-9 else np.degrees(x)), "deg"
    return table(x, r, unit=unit, source=(source + how) if source else None)


def _numbers(cells) -> bool:
    """Whether a row's first two cells are numbers (a data row, not a header)."""
    if len(cells) != 2:
        return False
    try:
        float(cells[0]), float(cells[1])
    except ValueError:
        return False
    return True


def profile(model) -> Profile:
    """The profile of an emission setting: None (Lambertian), a mapping or an object with
    ``model`` ('lambertian', 'diffuse' with ``refractive_index``, 'table' with ``angles`` (deg,
    or cos theta with ``unit: cos``) and ``radiance`` arrays; a table file is read by the
    caller, :func:`table_from_csv`)."""
    if model is None:
        return lambertian()
    if isinstance(model, Profile):
        return model

    def get(key, default=None):
        return model.get(key, default) if isinstance(model, dict) else getattr(model, key, default)

    kind = get("model", "lambertian")
    if kind == "lambertian":
        return lambertian()
    if kind == "diffuse":
        return diffuse(get("refractive_index", 1.40), tangential=bool(get("tangential_flux", True)),
                       depth=bool(get("depth_term", True)), curvature=bool(get("curvature_term", False)),
                       body=bool(get("body_curvature", True)),
                       reduced_scattering_per_mm=get("reduced_scattering_per_mm", DEFAULT_REDUCED_SCATTERING_PER_MM),
                       absorption_per_mm=get("absorption_per_mm", DEFAULT_ABSORPTION_PER_MM),
                       scattering_anisotropy=get("scattering_anisotropy", 0.0))
    if kind == "table":
        return table(get("angles"), get("radiance"), unit=get("unit", "deg"))
    raise ValueError(f"unknown emission model {kind!r} (lambertian, diffuse or table)")


def share_beyond(weights: np.ndarray, cos_theta: np.ndarray, degrees: float) -> float:
    """The share of ``weights`` whose emission angle exceeds ``degrees`` (NaN when none)."""
    w = np.asarray(weights, float)
    tot = float(np.sum(w))
    if not tot > 0:
        return float("nan")
    return float(np.sum(w[np.asarray(cos_theta) < np.cos(np.radians(degrees))])) / tot


def face_frames(face_vertices_mm: np.ndarray) -> np.ndarray:
    """Two in-plane unit vectors per triangle (F, 2, 3): e1 along its first edge, e2 = n x e1.
    They turn with the surface (a rigid placement turns them as it turns the face), so the
    tangential matrix T holds in these components is the same for the subject's own surface
    and for any pose of it.  Degenerate faces get zeros."""
    tri = np.asarray(face_vertices_mm, float)
    e1 = tri[:, 1] - tri[:, 0]
    nvec = np.cross(e1, tri[:, 2] - tri[:, 0])
    l1 = np.linalg.norm(e1, axis=1)
    ln = np.linalg.norm(nvec, axis=1)
    good = (l1 > 0) & (ln > 0)
    e1 = np.divide(e1, l1[:, None], out=np.zeros_like(e1), where=good[:, None])
    nhat = np.divide(nvec, ln[:, None], out=np.zeros_like(nvec), where=good[:, None])
    return np.stack([e1, np.cross(nhat, e1)], axis=1)


def tangent_operator(surface, levels: int = 1):
    """The tangential term's map from vertex unknowns to the fine faces T is built on
    (:meth:`fluxcli.surface.mesh.Surface.vertex_basis`, same orderings): sparse
    (2 n_fine, n_vertices), row 2f + a, column v: ``-S_f grad phi_v|_f . e_a / A_v`` (mm), e_a
    the fine face's in-plane unit vectors (:func:`face_frames`, the components T holds).

    With exitance linear within each face, ``M = sum_v phi_v u_v / A_v`` (u_v the lumped power
    of vertex v, A_v = int phi_v dS), its gradient on fine face f is the constant
    ``sum_v grad phi_v|_f u_v / A_v`` (the hat's gradient on the coarse face f lies in), in the
    face's plane.  The light the term sends to pixel i is ``-S_f grad_t M|_f . T_tangent[i, f]``;
    so T per vertex gains ``T_tangent @ tangent_operator``.  Per-element (or per-face) unknowns
    have no gradient inside an element: the term does not act on them."""
    import scipy.sparse as sp

    levels = int(levels)
    fine, _ = surface.refined(levels)
    vb = surface.vertex_basis(levels)
    ok = surface.element_of_face >= 0
    _, local = np.unique(surface.faces[ok], return_inverse=True)
    local = local.reshape(-1, 3)
    coarse = np.flatnonzero(np.tile(ok, 4**levels)) % len(surface.faces)  # refined(): children of i at t F + i
    rank = np.cumsum(ok) - 1
    tri = surface.vertices_mm[surface.faces[coarse]]  # (n_fine, 3, 3): the coarse face of each fine one
    fine_ok = fine.element_of_face >= 0
    S_f = fine.face_areas_mm2[fine_ok]
    frames = face_frames(fine.face_vertices_mm[fine_ok])
    nvec = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    two_a = np.linalg.norm(nvec, axis=1)
    good = two_a > 0
    nhat = np.divide(nvec, two_a[:, None], out=np.zeros_like(nvec), where=good[:, None])
    inv_av = np.divide(1.0, vb.areas_mm2, out=np.zeros_like(vb.areas_mm2), where=vb.areas_mm2 > 0)
    n_fine, n_v = len(S_f), len(vb.areas_mm2)
    rows, cols, vals = [], [], []
    for k in range(3):  # grad phi_k = n x (p_{k+2} - p_{k+1}) / 2a, pointing from the opposite edge to p_k
        edge = tri[:, (k + 2) % 3] - tri[:, (k + 1) % 3]
        grad = np.divide(np.cross(nhat, edge), two_a[:, None], out=np.zeros_like(edge), where=good[:, None])
        v = local[rank[coarse], k]
        for a in range(2):
            rows.append(2 * np.arange(n_fine) + a)
            cols.append(v)
            vals.append(-S_f * np.einsum("ij,ij->i", grad, frames[:, a]) * inv_av[v])
    G = sp.coo_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(2 * n_fine, n_v))
    return sp.csr_array(G.tocsr())


def vertex_sharing_pairs(faces: np.ndarray, owner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) pairs of owners (``owner[f]`` for each face: the face itself, or its element) whose
    faces share a vertex, through the faces around each vertex: every ordered pair, repeats and
    an owner with itself included."""
    corner_v, corner_o = faces.ravel(), np.repeat(owner, 3)
    order = np.argsort(corner_v, kind="stable")
    sv, so = corner_v[order], corner_o[order]
    start = np.searchsorted(sv, corner_v, side="left")
    count = np.searchsorted(sv, corner_v, side="right") - start
    pa = np.repeat(corner_o, count)
    pb = so[np.repeat(start, count) + (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count))]
    return pa, pb


def tangent_light(surface, power_per_element: np.ndarray, same_plane_cos: float = 0.8) -> np.ndarray:
    """What a forward image adds for the tangential flux of a truth given as power per face
    (``surface`` one face per element, as ``Surface.refined``): ``-S_f grad_t M|_f`` in each
    face's frame (:func:`face_frames`), (2 n_faces,), so that ``T_tangent @ this`` is the light
    the term sends to each pixel.  grad_t M on face f is the least-squares gradient of the
    exitances of the faces around it (sharing a vertex) that face nearly the same way
    (normals within ~37 deg: a box's other faces do not count, a faceted cylinder's
    neighbours do), in f's plane: exact for an exitance linear on a plane, borders included."""
    ok = surface.element_of_face >= 0
    faces = surface.faces[ok]
    el = surface.element_of_face[ok]
    S = surface.face_areas_mm2[ok]
    nrm = surface.face_normals[ok]
    cen = surface.vertices_mm[faces].mean(axis=1)
    frames = face_frames(surface.vertices_mm[faces])
    M = np.divide(np.asarray(power_per_element, float)[el], S, out=np.zeros(len(S)), where=S > 0)
    F = len(faces)
    pf, pg = vertex_sharing_pairs(faces, np.arange(F))
    keep = (pf != pg) & (np.einsum("ij,ij->i", nrm[pf], nrm[pg]) >= same_plane_cos)
    pf, pg = pf[keep], pg[keep]
    d = np.einsum("iaj,ij->ia", frames[pf], cen[pg] - cen[pf])  # in f's frame
    dm = M[pg] - M[pf]
    a11 = np.bincount(pf, d[:, 0] * d[:, 0], F)
    a12 = np.bincount(pf, d[:, 0] * d[:, 1], F)
    a22 = np.bincount(pf, d[:, 1] * d[:, 1], F)
    b1 = np.bincount(pf, d[:, 0] * dm, F)
    b2 = np.bincount(pf, d[:, 1] * dm, F)
    det = a11 * a22 - a12 * a12
    good = det > 1e-12 * np.maximum(a11 + a22, 1e-300) ** 2
    g1 = np.divide(a22 * b1 - a12 * b2, det, out=np.zeros(F), where=good)
    g2 = np.divide(a11 * b2 - a12 * b1, det, out=np.zeros(F), where=good)
    out = np.zeros((surface.n_elements, 2))
    out[el] = -S[:, None] * np.stack([g1, g2], axis=1)
    return out.ravel()


def element_geometry(surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per element of ``surface``: its area (mm^2), its area-weighted centroid (mm) and its unit
    area-weighted normal (zeros for an element without faces)."""
    ok = surface.element_of_face >= 0
    fe, fa = surface.element_of_face[ok], surface.face_areas_mm2[ok]
    E_n = surface.n_elements
    S = np.bincount(fe, fa, E_n)
    tri = surface.vertices_mm[surface.faces[ok]]
    cen = np.stack([np.bincount(fe, fa * tri[:, :, k].mean(axis=1), E_n) for k in range(3)], axis=1)
    cen = np.divide(cen, S[:, None], out=np.zeros_like(cen), where=S[:, None] > 0)
    nrm = np.stack([np.bincount(fe, fa * surface.face_normals[ok][:, k], E_n) for k in range(3)], axis=1)
    ln = np.linalg.norm(nrm, axis=1)[:, None]
    return S, cen, np.divide(nrm, ln, out=np.zeros_like(nrm), where=ln > 0)


def curvature_operator(surface, same_plane_cos: float = 0.8, radius_mm: float | None = None):
    """The curvature term's map from power per element to ``S_e lap_t M|_e`` per element:
    sparse (E, E), so that the light the term sends to pixel i is ``sum_e T[i, e] r_e (K @
    power)_e`` with ``r_e`` the profile's :meth:`Profile.curvature_ratio` at the element's emission
    angle (:func:`fluxcli.transfer_cache.curvature_ratios`).

    lap_t M at element e is the trace of the Hessian of the least-squares quadratic through the
    exitances (power / area) of e and of the elements around it that face nearly the same way
    (normals within ~37 deg, as :func:`tangent_light`: a box's other faces do not count, a
    faceted cylinder's neighbours do), at their centroids in e's tangent plane: exact for an
    exitance quadratic on a plane, and for a linear function on a sphere (its planar Hessian
    in the tangent plane is the Laplace-Beltrami operator's value there).  "Around": sharing a
    vertex, or with ``radius_mm`` every element whose centroid lies within it (a wider fit, for
    exitances known only as a value per element, whose steps a fit over its next neighbours
    would read as curvature).  An element whose neighbourhood cannot hold a quadratic (fewer than
    six elements in its plane around it, or all on a line) gets no term."""
    import scipy.sparse as sp

    ok = surface.element_of_face >= 0
    faces, fe = surface.faces[ok], surface.element_of_face[ok]
    E_n = surface.n_elements
    S, cen, nrm = element_geometry(surface)
    # an in-plane frame per element (any: the Laplacian does not depend on it)
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(nrm, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-300)[:, None]
    e2 = np.cross(nrm, e1)
    if radius_mm is not None:
        from scipy.spatial import cKDTree

        pp = cKDTree(cen).query_pairs(float(radius_mm), output_type="ndarray")
        pf, pg = np.concatenate([pp[:, 0], pp[:, 1]]), np.concatenate([pp[:, 1], pp[:, 0]])
    else:
        pf, pg = vertex_sharing_pairs(faces, fe)
    keep = (pf != pg) & (np.einsum("ij,ij->i", nrm[pf], nrm[pg]) >= same_plane_cos)
    pairs = np.unique(np.stack([pf[keep], pg[keep]], axis=1), axis=0)
    pf = np.concatenate([np.arange(E_n), pairs[:, 0]])
    pg = np.concatenate([np.arange(E_n), pairs[:, 1]])
    h = np.sqrt(np.maximum(S, 1e-300))  # each element's own scale: the fit is made in units of it
    delta = cen[pg] - cen[pf]
    d = np.stack([np.einsum("ij,ij->i", e1[pf], delta), np.einsum("ij,ij->i", e2[pf], delta)], axis=1) / h[pf, None]
    phi = np.stack([np.ones(len(pf)), d[:, 0], d[:, 1], d[:, 0] ** 2 / 2, d[:, 0] * d[:, 1], d[:, 1] ** 2 / 2], axis=1)
    outer = (phi[:, :, None] * phi[:, None, :]).reshape(len(pf), 36)
    N = np.stack([np.bincount(pf, outer[:, k], E_n) for k in range(36)], axis=1).reshape(E_n, 6, 6)
    ev = np.linalg.eigvalsh(N)
    good = (np.bincount(pf, minlength=E_n) >= 6) & (ev[:, 0] > 1e-6 * np.maximum(ev[:, -1], 1e-300))
    u = np.zeros((E_n, 6))
    rhs = np.broadcast_to(np.array([0, 0, 0, 1.0, 0, 1.0]), (int(good.sum()), 6))[..., None]
    u[good] = np.linalg.solve(N[good], rhs)[..., 0]
    w = np.einsum("ij,ij->i", u[pf], phi) / S[pf]  # lap_t M|_e = sum_g w_eg M_g (1/mm^2); N symmetric
    vals = S[pf] * w / np.where(S[pg] > 0, S[pg], np.inf)  # K @ power, with M_g = power_g / S_g
    return sp.csr_array(sp.coo_array((vals, (pf, pg)), shape=(E_n, E_n)).tocsr())


def curvature_regions(K) -> np.ndarray:
    """The region of each element for :func:`curvature_kappa`: the connected parts of the
    neighbourhood graph of :func:`curvature_operator` (elements near each other that face the
    same way: a box's six faces, a cylinder's round body and its two ends, a mouse's skin)."""
    from scipy.sparse.csgraph import connected_components

    A = abs(K)
    return connected_components(A + A.T, directed=False)[1]


def curvature_kappa(K, power_per_element: np.ndarray, regions: np.ndarray, kappa_max: float) -> np.ndarray:
    """``kappa = lap_t M / M`` (1/mm^2) per element of a power per element (unobserved or dark: 0),
    from ``K`` of :func:`curvature_operator`, with its power-weighted mean over each of
    ``regions`` (:func:`curvature_regions`) taken out, then clipped to ``|kappa| <= kappa_max``.

    Over a region the term carries no light between angles: the integral of a Laplacian over a
    surface without a border is zero, and on a finite face the photons agree (a face's light, all
    positions together, follows the profile band by band within 0.4 %: docs/accuracy.md §1.4).
    The least-squares fit is not conservative: at a face's border its neighbourhood is one-sided,
    and elements as wide as a spot flatten the peak while the tail keeps its curvature, so
    without this the term would tilt a whole face's light (the battery's box, 4-mm elements:
    mean kappa -0.012 /mm^2, its head-on total 0.998 -> 0.993; docs/design.md, "The curvature term")."""
    p = np.maximum(np.nan_to_num(np.asarray(power_per_element, float), nan=0.0), 0.0)
    kappa = np.divide(K @ p, p, out=np.zeros_like(p), where=p > 0)
    n = int(regions.max()) + 1 if regions.size else 0
    weight = np.bincount(regions, p, n)
    mean = np.divide(np.bincount(regions, kappa * p, n), weight, out=np.zeros(n), where=weight > 0)
    return np.clip(np.where(p > 0, kappa - mean[regions], 0.0), -kappa_max, kappa_max)


def curvature_power(surface, power_per_face: np.ndarray, profile: Profile,
                    radius_mm: float | None = None) -> np.ndarray:
    """``S_e lap_t M|_e`` per element of a truth given as power per element (simulate: the faces
    of its refined surface, one per element), with ``kappa = lap_t M / M`` of
    :func:`curvature_kappa` (its power-weighted mean over each region taken out,
    ``|kappa| l^2 <= KAPPA_L2_MAX``: the term is first order in it), so that
    ``load_T_curvature(...) @ this`` is the light the profile's curvature term sends to each pixel
    (:func:`curvature_operator`, :func:`curvature_ratio`)."""
    p = np.maximum(np.asarray(power_per_face, float), 0.0)
    K = curvature_operator(surface, radius_mm=radius_mm)
    transport = profile.reduced_scattering_per_mm + profile.absorption_per_mm
    return curvature_kappa(K, p, curvature_regions(K), KAPPA_L2_MAX * transport**2) * p
