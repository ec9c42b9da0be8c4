"""Linear tetrahedral finite elements for the diffusion approximation (as NIRFAST).

Solves, for the fluence rate φ (photons s⁻¹ mm⁻²),

    −∇·(D ∇φ) + μa φ = q,        D = 1 / (3 (μa + μs′))          in the subject,
    φ + 2 A D ∂φ/∂n = 0                                         on its boundary,

with q in photons s⁻¹ mm⁻³.  The weak form is

    ∫ D ∇φ·∇v + μa φ v dV + ∫ φ v / (2A) dS = ∫ q v dV,

and the exitance leaving the surface is J = φ / (2A) (photons s⁻¹ mm⁻²).  Taking
v = 1 shows that the discrete model conserves power: source power = absorbed power
+ ∫ J dS, exactly, for any mesh.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from ..surface.geometry import triangle_areas
from .mesh import boundary_faces, tet_volumes_mm3
from ..errors import InputError

__all__ = ["nirfast_A", "DiffusionModel", "ball_quadrature", "AMG_ABOVE_NODES", "SOLVERS"]

SOLVERS = ("auto", "direct", "amg")
# Above this many nodes ``solver="auto"`` uses algebraic multigrid + CG instead of SuperLU:
# the sparse LU's fill-in of a 3-D mesh grows roughly as n^(4/3)..n^(3/2) (minutes and many GB
# beyond ~10^5 nodes), the AMG-preconditioned CG's time and memory as n.
AMG_ABOVE_NODES = 100_000


def nirfast_A(refractive_index):
    """Boundary mismatch factor A of the Robin condition, as computed by NIRFAST.

    Parameters
    ----------
    refractive_index : float
        Refractive index n ≥ 1 of the tissue (outside is n = 1).

    Returns
    -------
    float
        A = (2/(1 − R0) − 1 + |cos θc|³) / (1 − |cos θc|²) with R0 = ((n − 1)/(n + 1))²
        and θc = asin(1/n).  A = 1 for n = 1.
    """
    n = float(refractive_index)
    if not np.isfinite(n) or n < 1:
        raise InputError(f"refractive index must be >= 1, got {refractive_index}.")
    r0 = ((n - 1) / (n + 1)) ** 2
    cos_c = abs(np.cos(np.arcsin(1 / n)))
    return float((2 / (1 - r0) - 1 + cos_c**3) / (1 - cos_c**2))


def ball_quadrature(n_per_diameter=16):
    """Equal-weight quadrature points filling the unit ball.

    Parameters
    ----------
    n_per_diameter : int
        Points per diameter of a cell-centred cubic grid; about 0.52 n³ points result.

    Returns
    -------
    ndarray, shape (n_points, 3)
        Points inside the unit ball, symmetric about the origin (each carries weight
        1/n_points of the ball).
    """
    t = (np.arange(n_per_diameter) + 0.5) / n_per_diameter * 2 - 1
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid[np.einsum("ij,ij->i", grid, grid) < 1]


def _per_tet(value, n_tets, name):
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n_tets, float(arr))
    if arr.shape != (n_tets,):
        raise InputError(f"{name} must be a number or have one value per tetrahedron ({n_tets}).")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite.")
    return arr


class DiffusionModel:
    """Diffusion-approximation forward model on a tetrahedral mesh.

    The system matrix is assembled at construction and factorised once, on the first
    solve; every later solve (any number of sources) reuses the factorisation.

    Parameters
    ----------
    nodes_mm : array_like, shape (n_nodes, 3)
        Node positions in mm.
    tets : array_like of int, shape (n_tets, 4)
        Positively oriented tetrahedra (as returned by
        :func:`fluxcli.diffusion.mesh.tetrahedralize`).
    mua_per_mm : float or array_like, shape (n_tets,)
        Absorption coefficient μa ≥ 0 in mm⁻¹ (0 allowed).
    musp_per_mm : float or array_like, shape (n_tets,)
        Reduced scattering coefficient μs′ > 0 in mm⁻¹.
    refractive_index : float
        Refractive index n ≥ 1 of the subject (outside is air, n = 1).
    solver : {"auto", "direct", "amg"}
        ``direct``: sparse LU (SuperLU), exact to round-off, factorised once for any number
        of sources. ``amg``: conjugate gradients preconditioned by smoothed-aggregation
        algebraic multigrid (pyamg), iterated until the residual ‖b − Kφ‖ ≤ ``rtol``·‖b‖
        per source; time and memory grow linearly with the mesh. ``auto``: ``amg`` above
        :data:`AMG_ABOVE_NODES` nodes, else ``direct``.
    rtol : float
        Relative residual at which ``amg`` stops (ignored by ``direct``).

    Attributes
    ----------
    A : float
        Robin boundary factor (:func:`nirfast_A`).
    diffusion_mm : ndarray, shape (n_tets,)
        Diffusion coefficient D in mm.
    boundary_faces : ndarray of int64, shape (n_boundary_faces, 3)
        Outward boundary triangles, indexing ``nodes_mm``.
    boundary_nodes : ndarray of int64, shape (n_boundary_nodes,)
        Nodes on the boundary; exitance arrays are indexed like this.
    solver : str
        The solver that runs: ``direct`` or ``amg`` (``auto`` resolved).
    residuals : list of float
        Relative residual ‖b − Kφ‖/‖b‖ of every source solved so far (``amg``; empty for ``direct``).
    """

    def __init__(self, nodes_mm, tets, *, mua_per_mm, musp_per_mm, refractive_index, solver="auto", rtol=1e-10):
        nodes_mm = np.ascontiguousarray(nodes_mm, dtype=np.float64)
        tets = np.asarray(tets)
        if nodes_mm.ndim != 2 or nodes_mm.shape[1] != 3:
            raise InputError(f"nodes must have shape (n, 3), got {nodes_mm.shape}.")
        if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
            raise InputError(f"tets must have shape (m, 4) with m > 0, got {tets.shape}.")
        tets = tets.astype(np.int64)
        if tets.min() < 0 or tets.max() >= len(nodes_mm):
            raise InputError("tets index nodes that do not exist.")
        n_tets = len(tets)
        mua = _per_tet(mua_per_mm, n_tets, "absorption coefficient mua_per_mm")
        musp = _per_tet(musp_per_mm, n_tets, "reduced scattering coefficient musp_per_mm")
        if np.any(mua < 0):
            raise InputError(f"absorption coefficient mua_per_mm must be >= 0, got min {mua.min()}.")
        if np.any(musp <= 0):
            raise InputError(
                f"reduced scattering coefficient musp_per_mm must be > 0, got min {musp.min()}."
            )
        if solver not in SOLVERS:
            raise InputError(f"solver must be one of {', '.join(SOLVERS)}, got {solver!r}.")
        if not (np.isfinite(rtol) and 0 < rtol < 1):
            raise InputError(f"solver tolerance rtol must lie in (0, 1), got {rtol}.")
        self.solver = solver if solver != "auto" else ("amg" if len(nodes_mm) > AMG_ABOVE_NODES else "direct")
        self.rtol = float(rtol)
        self.residuals: list[float] = []
        self.A = nirfast_A(refractive_index)
        self.refractive_index = float(refractive_index)
        self.nodes_mm = nodes_mm
        self.tets = tets
        self.mua_per_mm = mua
        self.diffusion_mm = 1.0 / (3.0 * (mua + musp))

        self.volumes_mm3 = tet_volumes_mm3(nodes_mm, tets)
        if np.any(self.volumes_mm3 <= 0):
            raise InputError("tets must all have positive volume (orient them as tetrahedralize does).")
        self.boundary_faces = boundary_faces(tets)
        self.boundary_nodes = np.unique(self.boundary_faces)
        self.boundary_areas_mm2 = triangle_areas(nodes_mm[self.boundary_faces])

        self._stiffness_plus_absorption = self._assemble_volume()
        self._boundary_mass = _assemble_surface_mass(
            nodes_mm, self.boundary_faces, self.boundary_areas_mm2, len(nodes_mm)
        )
        self.system_matrix = (
            self._stiffness_plus_absorption + self._boundary_mass / (2.0 * self.A)
        ).tocsc()
        self._lu = None
        self._amg = None
        self._centroid_tree = None

    # ------------------------------------------------------------------ assembly
    def _assemble_volume(self):
        p = self.nodes_mm[self.tets]  # (m, 4, 3)
        edges = p[:, 1:] - p[:, :1]  # rows p_i - p_0
        inv = np.linalg.inv(edges)  # λ' = (x - p0) @ inv
        grads = np.empty((len(self.tets), 4, 3))
        grads[:, 1:] = np.swapaxes(inv, 1, 2)
        grads[:, 0] = -grads[:, 1:].sum(axis=1)
        vol = self.volumes_mm3
        k_local = (vol * self.diffusion_mm)[:, None, None] * np.einsum("mik,mjk->mij", grads, grads)
        m_local = (vol * self.mua_per_mm / 20.0)[:, None, None] * (np.ones((4, 4)) + np.eye(4))
        rows = np.repeat(self.tets, 4, axis=1).ravel()
        cols = np.tile(self.tets, (1, 4)).ravel()
        n = len(self.nodes_mm)
        return sp.csr_matrix(((k_local + m_local).ravel(), (rows, cols)), shape=(n, n))

    # ------------------------------------------------------------------ sources
    def locate_points(self, points_mm):
        """Find the tetrahedron containing each point and its barycentric coordinates.

        Parameters
        ----------
        points_mm : array_like, shape (n_points, 3)
            Positions in mm.

        Returns
        -------
        tet_index : ndarray of int64, shape (n_points,)
            Containing tetrahedron, or -1 for points outside the mesh.
        barycentric : ndarray, shape (n_points, 4)
            Barycentric coordinates in that tetrahedron (NaN where outside).
        """
        points_mm = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
        n_points = len(points_mm)
        tet_index = np.full(n_points, -1, dtype=np.int64)
        bary = np.full((n_points, 4), np.nan)
        if self._centroid_tree is None:
            self._centroid_tree = cKDTree(self.nodes_mm[self.tets].mean(axis=1))
        k = min(16, len(self.tets))
        _, cand = self._centroid_tree.query(points_mm, k=k)
        cand = cand.reshape(n_points, k)
        lam = self._barycentric(points_mm[:, None, :], cand)  # (n_points, k, 4)
        best = np.argmax(lam.min(axis=2), axis=1)
        rows = np.arange(n_points)
        ok = lam[rows, best].min(axis=1) >= -1e-9
        tet_index[ok] = cand[rows, best][ok]
        bary[ok] = lam[rows, best][ok]
        # Rare fall-back (points near badly shaped tets): test every tet whose box holds the point.
        if not np.all(ok):
            p = self.nodes_mm[self.tets]
            lo, hi = p.min(axis=1), p.max(axis=1)
            for i in np.flatnonzero(~ok):
                x = points_mm[i]
                inside_box = np.flatnonzero(np.all((lo <= x + 1e-9) & (hi >= x - 1e-9), axis=1))
                if len(inside_box) == 0:
                    continue
                lam_i = self._barycentric(x[None, None, :], inside_box[None, :])[0]
                j = np.argmax(lam_i.min(axis=1))
                if lam_i[j].min() >= -1e-9:
                    tet_index[i], bary[i] = inside_box[j], lam_i[j]
        return tet_index, bary

    def _barycentric(self, x, tet_ids):
        p = self.nodes_mm[self.tets[tet_ids]]  # (..., 4, 3)
        inv = np.linalg.inv(p[..., 1:, :] - p[..., :1, :])
        lam = np.einsum("...k,...kj->...j", x - p[..., 0, :], inv)
        return np.concatenate([1 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)

    def _check_sources(self, positions_mm, power_photons_s):
        positions_mm = np.atleast_2d(np.asarray(positions_mm, dtype=np.float64))
        if positions_mm.ndim != 2 or positions_mm.shape[1] != 3:
            raise InputError(f"source positions must have shape (n, 3), got {positions_mm.shape}.")
        try:
            power = np.broadcast_to(np.asarray(power_photons_s, dtype=np.float64), len(positions_mm))
        except ValueError:
            raise InputError("source power must be a number or one value per source.") from None
        if not np.all(np.isfinite(power)) or np.any(power < 0):
            raise InputError("source power must be finite and >= 0 photons/s.")
        return positions_mm, power

    def _rhs_from_points(self, points_mm, weights, source_of_point, n_sources, what):
        tet_index, bary = self.locate_points(points_mm)
        outside = np.flatnonzero(tet_index < 0)
        if len(outside):
            x, y, z = points_mm[outside[0]]
            raise InputError(f"{what} at ({x:.3f}, {y:.3f}, {z:.3f}) mm lies outside the subject.")
        rows = self.tets[tet_index].ravel()
        cols = np.repeat(source_of_point, 4)
        vals = (bary * weights[:, None]).ravel()
        rhs = sp.coo_matrix((vals, (rows, cols)), shape=(len(self.nodes_mm), n_sources))
        return rhs.toarray()

    def point_source_rhs(self, positions_mm, power_photons_s):
        """Right-hand sides for isotropic point sources.

        Parameters
        ----------
        positions_mm : array_like, shape (n_sources, 3)
            Source positions in mm; each must lie inside the mesh.
        power_photons_s : float or array_like, shape (n_sources,)
            Emitted power of each source in photons/s.

        Returns
        -------
        ndarray, shape (n_nodes, n_sources)
            Load vectors, P times the barycentric weights of the containing tetrahedron.
        """
        positions_mm, power = self._check_sources(positions_mm, power_photons_s)
        n = len(positions_mm)
        return self._rhs_from_points(positions_mm, power, np.arange(n), n, "source")

    def sphere_source_rhs(self, centres_mm, radius_mm, power_photons_s, *, n_per_diameter=16):
        """Right-hand sides for small balls emitting uniformly through their volume.

        Parameters
        ----------
        centres_mm : array_like, shape (n_sources, 3)
            Ball centres in mm.
        radius_mm : float or array_like, shape (n_sources,)
            Ball radii in mm (> 0); the whole ball must lie inside the mesh.
        power_photons_s : float or array_like, shape (n_sources,)
            Total emitted power of each ball in photons/s.
        n_per_diameter : int
            Resolution of the equal-weight quadrature (:func:`ball_quadrature`).

        Returns
        -------
        ndarray, shape (n_nodes, n_sources)
            Load vectors ∫ q ψ_i dV, summing to the source power.
        """
        centres_mm, power = self._check_sources(centres_mm, power_photons_s)
        try:
            radius = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), len(centres_mm))
        except ValueError:
            raise InputError("source radius_mm must be a number or one value per source.") from None
        if not np.all(np.isfinite(radius)) or np.any(radius <= 0):
            raise InputError("source radius_mm must be > 0.")
        q = ball_quadrature(n_per_diameter)
        points = (centres_mm[:, None, :] + radius[:, None, None] * q[None]).reshape(-1, 3)
        weights = np.repeat(power / len(q), len(q))
        owner = np.repeat(np.arange(len(centres_mm)), len(q))
        return self._rhs_from_points(points, weights, owner, len(centres_mm), "part of a sphere source")

    def source_rhs(self, positions_mm, radii_mm, power_photons_s):
        """Right-hand sides for a mix of point sources (radius 0) and uniform balls.

        Parameters
        ----------
        positions_mm : array_like, shape (n_sources, 3)
            Source positions (ball centres) in mm.
        radii_mm : float or array_like, shape (n_sources,)
            0 for an isotropic point source, else the ball radius in mm.
        power_photons_s : float or array_like, shape (n_sources,)
            Emitted power of each source in photons/s.

        Returns
        -------
        ndarray, shape (n_nodes, n_sources)
        """
        positions_mm, power = self._check_sources(positions_mm, power_photons_s)
        try:
            radii = np.broadcast_to(np.asarray(radii_mm, dtype=np.float64), len(positions_mm))
        except ValueError:
            raise InputError("source radii_mm must be a number or one value per source.") from None
        if not np.all(np.isfinite(radii)) or np.any(radii < 0):
            raise InputError("source radii_mm must be >= 0 (0 for a point source).")
        rhs = np.empty((len(self.nodes_mm), len(positions_mm)))
        point = radii == 0
        if np.any(point):
            rhs[:, point] = self.point_source_rhs(positions_mm[point], power[point])
        if np.any(~point):
            rhs[:, ~point] = self.sphere_source_rhs(positions_mm[~point], radii[~point], power[~point])
        return rhs

    # ------------------------------------------------------------------ solving
    def solve(self, rhs):
        """Fluence rate for one or many right-hand sides (factorises on first call).

        Parameters
        ----------
        rhs : array_like, shape (n_nodes,) or (n_nodes, n_sources)
            Load vectors in photons/s (from the ``*_rhs`` methods).

        Returns
        -------
        ndarray, same shape as ``rhs``
            Nodal fluence rate φ in photons s⁻¹ mm⁻².
        """
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.shape[0] != len(self.nodes_mm):
            raise InputError(f"rhs must have {len(self.nodes_mm)} rows, got {rhs.shape[0]}.")
        if self.solver == "amg":
            return self._solve_amg(rhs)
        if self._lu is None:
            # The matrix is symmetric positive definite: a symmetric ordering without
            # off-diagonal pivoting is exact and ~20x faster than SuperLU's defaults.
            self._lu = spla.splu(
                self.system_matrix,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options=dict(SymmetricMode=True),
            )
        return self._lu.solve(rhs)

    def _solve_amg(self, rhs):
        """CG preconditioned by one smoothed-aggregation V-cycle, per right-hand side."""
        if self._amg is None:
            import pyamg

            K = self.system_matrix.tocsr()
            # the matrix is symmetric positive definite; its near-null space is the constants
            self._amg = (K, pyamg.smoothed_aggregation_solver(K, symmetry="symmetric", max_coarse=500)
                         .aspreconditioner(cycle="V"))
        K, M = self._amg
        cols = rhs.reshape(len(rhs), -1)
        out = np.zeros_like(cols)
        for j in range(cols.shape[1]):
            b = cols[:, j]
            nb = float(np.linalg.norm(b))
            if nb == 0:
                self.residuals.append(0.0)
                continue
            x, info = spla.cg(K, b, rtol=self.rtol, atol=0.0, maxiter=2000, M=M)
            res = float(np.linalg.norm(b - K @ x)) / nb
            if info != 0 or res > 10 * self.rtol:
                raise InputError(f"the AMG-preconditioned CG did not converge (relative residual {res:.2e}, "
                                 f"asked for {self.rtol:.0e}); use the direct solver.")
            self.residuals.append(res)
            out[:, j] = x
        return out.reshape(rhs.shape)

    def exitance_at_boundary_nodes(self, fluence):
        """Exitance J = φ/(2A) at ``boundary_nodes`` in photons s⁻¹ mm⁻².

        Parameters
        ----------
        fluence : ndarray, shape (n_nodes,) or (n_nodes, n_sources)
            Nodal fluence rate from :meth:`solve`.

        Returns
        -------
        ndarray, shape (n_boundary_nodes,) or (n_boundary_nodes, n_sources)
        """
        return np.asarray(fluence)[self.boundary_nodes] / (2.0 * self.A)

    def total_exitance_photons_s(self, fluence):
        """Power leaving through the boundary, ∫ J dS, integrated exactly (photons/s).

        Parameters
        ----------
        fluence : ndarray, shape (n_nodes,) or (n_nodes, n_sources)

        Returns
        -------
        float or ndarray, shape (n_sources,)
        """
        return np.asarray(self._boundary_mass.sum(axis=0)).ravel() @ fluence / (2.0 * self.A)

    def absorbed_power_photons_s(self, fluence):
        """Power absorbed in the volume, ∫ μa φ dV (photons/s).

        Parameters
        ----------
        fluence : ndarray, shape (n_nodes,) or (n_nodes, n_sources)

        Returns
        -------
        float or ndarray, shape (n_sources,)
        """
        node_weight = np.zeros(len(self.nodes_mm))
        np.add.at(node_weight, self.tets.ravel(), np.repeat(self.volumes_mm3 * self.mua_per_mm / 4, 4))
        return node_weight @ fluence

    def boundary_surface(self):
        """The mesh boundary as a stand-alone triangle surface.

        Returns
        -------
        vertices_mm : ndarray, shape (n_boundary_nodes, 3)
            Positions of ``boundary_nodes`` in mm.
        faces : ndarray of int64, shape (n_boundary_faces, 3)
            Outward triangles indexing ``vertices_mm`` (same order as exitance arrays).
        """
        local = np.searchsorted(self.boundary_nodes, self.boundary_faces)
        return self.nodes_mm[self.boundary_nodes], local


def _assemble_surface_mass(vertices_mm, faces, areas_mm2, n_nodes):
    """Consistent mass matrix ∫ ψ_i ψ_j dS of linear triangles."""
    local = (areas_mm2 / 12.0)[:, None, None] * (np.ones((3, 3)) + np.eye(3))
    rows = np.repeat(faces, 3, axis=1).ravel()
    cols = np.tile(faces, (1, 3)).ravel()
    return sp.csr_matrix((local.ravel(), (rows, cols)), shape=(n_nodes, n_nodes))
