"""Triangle surfaces whose faces are grouped into flux elements.

A :class:`Surface` is the unit every stage passes around: vertices in mm, triangular
faces wound counter-clockwise seen from outside (the emitting side), and the element
each face belongs to (``-1`` for faces that only occlude, such as the unmeshed caps of a
cylinder phantom).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .geometry import triangle_areas


@dataclass(frozen=True)
class Surface:
    """A triangulated surface with faces grouped into elements.

    Attributes
    ----------
    vertices_mm : (V, 3) float64
    faces : (F, 3) int64, counter-clockwise seen from the emitting side.
    element_of_face : (F,) int64, element index in ``[0, n_elements)`` or -1 (occluder only).
    n_elements : int
    """

    vertices_mm: np.ndarray
    faces: np.ndarray
    element_of_face: np.ndarray
    n_elements: int
    element_ids: np.ndarray | None = field(default=None, compare=False)
    subelement_of_face: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "vertices_mm", np.ascontiguousarray(self.vertices_mm, dtype=np.float64))
        object.__setattr__(self, "faces", np.ascontiguousarray(self.faces, dtype=np.int64))
        object.__setattr__(self, "element_of_face", np.ascontiguousarray(self.element_of_face, dtype=np.int64))

    # ------------------------------------------------------------------ geometry
    @property
    def face_vertices_mm(self) -> np.ndarray:
        """(F, 3, 3) corner coordinates."""
        return self.vertices_mm[self.faces]

    @property
    def face_areas_mm2(self) -> np.ndarray:
        return triangle_areas(self.face_vertices_mm)

    @property
    def face_normals(self) -> np.ndarray:
        t = self.face_vertices_mm
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    @property
    def element_areas_mm2(self) -> np.ndarray:
        """(n_elements,) area S_j of each element."""
        m = self.element_of_face >= 0
        return np.bincount(self.element_of_face[m], weights=self.face_areas_mm2[m], minlength=self.n_elements)

    @property
    def element_centroids_mm(self) -> np.ndarray:
        m = self.element_of_face >= 0
        a = self.face_areas_mm2[m]
        c = self.face_vertices_mm[m].mean(axis=1)
        e = self.element_of_face[m]
        out = np.stack([np.bincount(e, weights=a * c[:, k], minlength=self.n_elements) for k in range(3)], axis=1)
        return out / np.maximum(self.element_areas_mm2, 1e-300)[:, None]

    @property
    def element_normals(self) -> np.ndarray:
        m = self.element_of_face >= 0
        an = self.face_normals[m] * self.face_areas_mm2[m, None]
        e = self.element_of_face[m]
        out = np.stack([np.bincount(e, weights=an[:, k], minlength=self.n_elements) for k in range(3)], axis=1)
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)

    def element_adjacency(self):
        """Sparse (n_elements, n_elements) 0/1 matrix: 1 where two elements share a vertex."""
        import scipy.sparse as sp

        ok = self.element_of_face >= 0
        rows = np.repeat(self.element_of_face[ok], 3)
        inc = sp.csr_matrix((np.ones(len(rows)), (rows, self.faces[ok].ravel())),
                            shape=(self.n_elements, len(self.vertices_mm)))
        adj = (inc @ inc.T).tocsr()
        adj.setdiag(0)
        adj.eliminate_zeros()
        adj.data[:] = 1.0
        return adj

    def boundary_edge_count(self) -> int:
        """Number of edges not shared by exactly two faces (0 for a closed manifold)."""
        return int(np.count_nonzero(edge_face_counts(self.faces) != 2))

    @property
    def is_closed(self) -> bool:
        return len(self.faces) > 0 and self.boundary_edge_count() == 0

    # ------------------------------------------------------------------ placement
    def transformed(self, rotation: np.ndarray, translation_mm: np.ndarray) -> "Surface":
        """x -> R x + t (R proper or improper; an improper R flips the winding)."""
        v = self.vertices_mm @ np.asarray(rotation).T + np.asarray(translation_mm)
        faces = self.faces if np.linalg.det(rotation) > 0 else self.faces[:, ::-1]
        return Surface(v, faces, self.element_of_face, self.n_elements, self.element_ids, self.subelement_of_face)

    def subdivided(self, levels: int = 1, body=None) -> "Surface":
        """The same elements on finer faces: every triangle split into 4 (edge midpoints)
        ``levels`` times, each fine face in its coarse face's element. The light within an element
        is modelled per face (linear within each, for vertex unknowns), so finer faces follow a
        spot that is about an element wide; the elements, what is reported, are unchanged.

        ``body`` (a phantom's :class:`~fluxcli.surface.phantoms.RoundBody`, or None): the curved
        surface the coarse vertices lie on. The midpoint of an edge whose two ends lie on it is
        moved onto it, so the finer faces follow the round body (a cylinder's 20 facets become
        40 around) rather than the flat facets between its vertices."""
        if int(levels) == 0:
            return self
        v, f, eof = self._split_faces(levels, body)
        sub = None if self.subelement_of_face is None else np.tile(self.subelement_of_face, 4 ** int(levels))
        return Surface(v, f, eof, self.n_elements, self.element_ids, sub)

    def _split_faces(self, levels: int, body=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices, faces, element of each face) with every triangle split into 4 at its edge
        midpoints ``levels`` times; fine face k of a split is face k mod F of the coarser surface.
        With ``body``, midpoints of edges whose ends both lie on it are moved onto it."""
        v, f, eof = self.vertices_mm, self.faces, self.element_of_face
        for _ in range(int(levels)):
            edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
            uniq, inv = np.unique(edges, axis=0, return_inverse=True)
            mid = len(v) + inv.reshape(-1, 3)  # midpoint vertex of edges (01, 12, 20)
            centre = 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])
            if body is not None:
                on = body.holds(v[uniq[:, 0]]) & body.holds(v[uniq[:, 1]])
                centre[on] = body.project(centre[on])
            v = np.concatenate([v, centre])
            a, b, c = f[:, 0], f[:, 1], f[:, 2]
            ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
            f = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
            eof = np.tile(eof, 4)
        return v, f, eof

    def unknowns(self) -> tuple["Surface", np.ndarray]:
        """The finer grid a reconstruction may solve on, and the element each part belongs to.

        The parts are the generator's sub-elements (e.g. the ring's strips along the arc)
        or, without them, every face that belongs to an element.
        """
        if self.subelement_of_face is not None:
            sub = self.subelement_of_face
        else:
            sub = np.where(self.element_of_face >= 0, np.arange(len(self.faces)), -1)
        ok = sub >= 0
        ids, inv = np.unique(sub[ok], return_inverse=True)
        eof = np.full(len(self.faces), -1, np.int64)
        eof[ok] = inv
        parent = np.zeros(len(ids), np.int64)
        parent[inv] = self.element_of_face[ok]
        return Surface(self.vertices_mm, self.faces, eof, len(ids)), parent

    def refined(self, levels: int = 1) -> tuple["Surface", np.ndarray]:
        """The same surface with every triangle split into 4 (edge midpoints) ``levels``
        times; each fine face that belongs to an element becomes its own element.

        What an honest simulation puts its truth on: finer than the elements that are
        reconstructed, summed back per element with the returned parent.

        Returns
        -------
        fine : Surface, n_elements = number of fine faces with an element; faces with
            element -1 (occluders only) stay -1.
        parent : (fine.n_elements,) int64, the element of this surface each fine one is in.
            ``levels=0`` returns this surface and the identity.
        """
        if int(levels) == 0:  # no refinement: the elements themselves
            return self, np.arange(self.n_elements, dtype=np.int64)
        v, f, eof = self._split_faces(levels)
        ok = eof >= 0
        fine_eof = np.full(len(f), -1, np.int64)
        fine_eof[ok] = np.arange(int(ok.sum()))
        return Surface(v, f, fine_eof, int(ok.sum())), eof[ok].astype(np.int64)

    def vertex_basis(self, levels: int = 1) -> "VertexBasis":
        """Exitance linear within each face and continuous across edges: one unknown per
        vertex of the element faces (the hat function φ_v, 1 at v, 0 at the other vertices).

        A constant per face or element is a poor model where the camera resolves the
        surface and the light varies steeply across an element (towards a source at the
        limb or behind it): no value per element reproduces the image, and the best fit is
        biased even on noiseless data. The hat functions follow such a gradient.

        The unknown of vertex v is its lumped power ``u_v = J_v A_v`` (photons), with
        ``A_v = ∫φ_v dS`` and ``J_v`` the exitance at v (photons mm⁻²). T is built per face
        of :meth:`refined` (``levels`` times): a fine face's power is ``∫_f J dS = S_f Σ_v φ_v(c_f)
        J_v`` exactly (φ_v is linear on the fine face; c_f its centroid), and the only
        approximation is that T spreads it uniformly over that quarter of a face.

        Parameters
        ----------
        levels : int, how often the faces T is built on are split into 4 (1: quarters).

        Returns
        -------
        VertexBasis
        """
        import scipy.sparse as sp

        fine, parent = self.refined(levels)
        ok = self.element_of_face >= 0
        used, local = np.unique(self.faces[ok], return_inverse=True)
        local = local.reshape(-1, 3)
        # coarse face of each fine element: refined() lists the children of face i at t*F + i
        fine_ok = np.tile(ok, 4 ** int(levels))
        coarse = np.flatnonzero(fine_ok) % len(self.faces)  # index into all faces
        rank = np.cumsum(ok) - 1  # index into the element faces
        tri = self.vertices_mm[self.faces[coarse]]  # (n_fine, 3, 3)
        c = fine.face_vertices_mm[fine.element_of_face >= 0].mean(axis=1)
        n_fine, n_v = len(c), len(used)
        S_f = fine.face_areas_mm2[fine.element_of_face >= 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            bary = np.where(S_f[:, None] > 0, _barycentric(tri, c), 1.0 / 3.0)  # degenerate faces carry no area
        W = sp.csr_array((np.ravel(S_f[:, None] * bary), (np.repeat(np.arange(n_fine), 3),
                                                           local[rank[coarse]].ravel())), shape=(n_fine, n_v))
        A_v = np.asarray(W.sum(axis=0)).ravel()  # ∫φ_v dS
        inv = np.divide(1.0, A_v, out=np.zeros_like(A_v), where=A_v > 0)  # a vertex of degenerate faces only: no light
        to_fine = sp.csr_array(W @ sp.diags_array(inv))
        P = sp.csr_array((np.ones(n_fine), (parent, np.arange(n_fine))), shape=(self.n_elements, n_fine))
        e = np.sort(local[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        adj = sp.csr_array((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_v, n_v))
        adj = sp.csr_array(((adj + adj.T) > 0).astype(np.float64))
        K = cotangent_weights(self.vertices_mm[used], local)
        e_all = np.sort(local[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, count = np.unique(e_all, axis=0, return_counts=True)
        rim = np.zeros(n_v, bool)
        rim[edges[count != 2].ravel()] = True  # on the edge of an open surface (or of a non-manifold one)
        return VertexBasis(fine, to_fine, sp.csr_array(P @ to_fine), A_v, adj, used, K, rim)

    def digest(self) -> str:
        """Content hash of the placed geometry (rounded to 1 nm, so float noise does not matter)."""
        h = hashlib.sha256()
        h.update(np.round(self.vertices_mm, 6).astype("<f8").tobytes())
        h.update(self.faces.astype("<i8").tobytes())
        h.update(self.element_of_face.astype("<i8").tobytes())
        return h.hexdigest()

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices_mm.min(axis=0), self.vertices_mm.max(axis=0)


@dataclass(frozen=True)
class VertexBasis:
    """Unknowns per vertex (:meth:`Surface.vertex_basis`): exitance linear within a face.

    Attributes
    ----------
    fine : Surface, every element face split into 4; T is built with a column per fine face.
    to_fine : sparse (n_fine, n_vertices), power of each fine face per photon of a vertex's
        lumped power (T per vertex = T_fine @ to_fine).
    to_elements : sparse (n_elements, n_vertices), element power per photon of lumped
        power; every column sums to 1.
    areas_mm2 : (n_vertices,) ``A_v = ∫φ_v dS``; exitance at v = u_v / A_v.
    adjacency : sparse (n_vertices, n_vertices), 1 where two vertices share an edge.
    vertex_index : (n_vertices,) the surface vertex each unknown is.
    stiffness : sparse (n_vertices, n_vertices), the edge weights of ``∫|∇J|² dS`` for an
        exitance linear within each face (:func:`cotangent_weights`): the smoothness prior
        of a solve on vertices.
    on_boundary : (n_vertices,) bool, on the edge of an open surface.
    """

    fine: "Surface"
    to_fine: object
    to_elements: object
    areas_mm2: np.ndarray
    adjacency: object
    vertex_index: np.ndarray
    stiffness: object = None
    on_boundary: np.ndarray | None = None  # (n_vertices,) bool: on an edge used by one face only

    @property
    def n_vertices(self) -> int:
        return len(self.areas_mm2)

    def per_element(self, fine_to_elements=None) -> "ElementHats":
        """One unknown per element with the exitance still linear within each face and
        continuous across edges: the exitance at a vertex is the mean of the element values
        around it, each weighted by the share of the vertex's hat that lies on that element
        (:class:`ElementHats`). ``fine_to_elements`` (sparse (n_fine, n_elements), 1 where a
        face of :attr:`fine` lies on the element) lets :meth:`ElementHats.seen_basis` tell an
        element the camera sees from one it only sees the edges of."""
        import scipy.sparse as sp

        A = np.asarray(self.areas_mm2, dtype=np.float64)
        share = sp.csr_array(sp.csr_array(self.to_elements).T)  # (n_v, n_e): A_v^e / A_v, rows sum to 1
        S = np.asarray(share.T @ A).ravel()  # S_e = Σ_v A_v^e
        K = sp.csr_array(self.stiffness if self.stiffness is not None else self.adjacency)
        L = sp.csr_array(sp.diags_array(np.asarray(K.sum(axis=1)).ravel()) - K)
        boundary = np.zeros(len(A), bool) if self.on_boundary is None else np.asarray(self.on_boundary, bool)
        return ElementHats(share, A, S, L, sp.csr_array(self.to_elements), boundary, sp.csr_array(self.to_fine),
                           None if fine_to_elements is None else sp.csr_array(fine_to_elements))


OWN_SIGHT_MIN = 0.25  # ElementHats.seen_basis: an element seen at < 1/4 of its fringe's rate has no unknown


@dataclass(frozen=True)
class ElementHats:
    """One unknown per element, exitance linear within faces (:meth:`VertexBasis.per_element`).

    With ``A_v^e = ∫_e φ_v dS`` (``Σ_e A_v^e = A_v``, ``Σ_v A_v^e = S_e``) and the element
    value ``j_e = c_e / S_e`` (photons mm⁻²), the exitance at an inner vertex v is the mean
    ``J_v = Σ_e w_ve j_e / Σ_e w_ve`` with ``w_ve = A_v^e / A_v`` over the elements around it,
    and its lumped power ``u_v = A_v J_v``: ``u = P c`` with ``P ≥ 0``, so ``c ≥ 0`` keeps the
    exitance non-negative everywhere. A constant exitance is represented exactly, and so is
    a linear one at every vertex whose elements' centroids surround it symmetrically.

    A mean is one-sided where some of a vertex's elements are not in the solve (the camera
    does not see them) or where the surface ends: there it would hold the exitance flat
    towards the edge (a blob beyond the edge: 4-6x too much light on the grazing elements of
    the last row, where free vertices fit). Such *rim* vertices keep an unknown of their own,
    the lumped power ``u_v`` as on vertices; vertices with no element in the solve have none
    (``J_v = 0``). The unknowns are the elements (columns of elements not in the solve are 0)
    followed by the rim vertices (:meth:`basis`).

    The prior is the vertices' ``∫|∇J|² dS`` written on the unknowns: ``xᵀ (Qᵀ L_K Q) x`` in
    exitance units (``J = Q x``) with ``L_K`` the cotangent Laplacian. ``Qᵀ L_K Q`` has zero
    row sums, so it is the graph Laplacian of its negated off-diagonal; a positive
    off-diagonal (a negative weight) is clipped at 0 as :func:`cotangent_weights` clips
    obtuse angles.

    Attributes
    ----------
    share : sparse (n_vertices, n_elements), ``w_ve = A_v^e / A_v``.
    vertex_areas_mm2 : (n_vertices,) ``A_v``.
    areas_mm2 : (n_elements,) ``S_e``; the element value of exitance is ``c_e / S_e``.
    laplacian : sparse (n_vertices, n_vertices), ``L_K`` (cotangent).
    vertex_to_elements : sparse (n_elements, n_vertices), element power per photon of a
        vertex's lumped power (:attr:`VertexBasis.to_elements`).
    on_boundary : (n_vertices,) bool, on the edge of an open surface.
    to_fine : sparse (n_fine, n_vertices), power of each face of :attr:`VertexBasis.fine`
        per photon of a vertex's lumped power.
    fine_to_elements : sparse (n_fine, n_elements), 1 where a fine face lies on the element
        (None: :meth:`seen_basis` cannot test the elements and is :meth:`basis`).
    """

    share: object
    vertex_areas_mm2: np.ndarray
    areas_mm2: np.ndarray
    laplacian: object
    vertex_to_elements: object
    on_boundary: np.ndarray
    to_fine: object = None
    fine_to_elements: object = None

    def own_sight(self, b: "HatBasis", fine_sight: np.ndarray) -> np.ndarray:
        """Per element unknown of ``b``: how well the camera sees the light it puts on its own
        faces along its border, relative to the light it puts across the border on its
        neighbours' faces. Both through the hats of the vertices it shares with its
        neighbours, which reach one face into each side: the sensitivity is compared across
        the border at the scale of a face, not of an element.

        ``fine_sight`` (n_fine,) is the detection per photon of each fine face (T's column
        sums over the pixels used). With ``d_own`` the photons detected per photon the shared
        vertices' hats put on the element's own faces and ``d_fringe`` the same on its
        neighbours' faces, returns ``d_own / d_fringe`` (inf where the unknown has no fringe
        or the fringe is not seen; NaN for an element that is not an unknown of ``b``). About
        1 where the sensitivity is continuous across the border, view angles towards the
        silhouette included (a face's step in cos θ); far below 1 across a step in it: a
        crease or an occlusion edge beyond which the element's own faces are hidden (facing
        away, or behind something), so that the data see only the vertices it shares with
        seen elements."""
        import scipy.sparse as sp

        n_e = self.share.shape[1]
        shared = np.diff(sp.csr_array(self.share).indptr) >= 2  # a vertex whose hat lies on 2+ elements
        border = sp.csr_array(sp.diags_array(shared.astype(np.float64)) @ sp.csr_array(b.prolong[:, :n_e]))
        fine_pow = sp.csr_array(self.to_fine @ border)  # (n_fine, n_e) photons of the shared vertices' hats
        seen = sp.csr_array(fine_pow.multiply(np.asarray(fine_sight, np.float64)[:, None]))
        F = sp.csr_array(self.fine_to_elements.T)  # (n_e, n_fine)
        photons, detected = sp.csr_array(F @ fine_pow), sp.csr_array(F @ seen)  # (n_e elements, n_e unknowns)
        own_p, own_d = photons.diagonal(), detected.diagonal()
        fr_p = np.asarray(photons.sum(axis=0)).ravel() - own_p
        fr_d = np.asarray(detected.sum(axis=0)).ravel() - own_d
        with np.errstate(invalid="ignore", divide="ignore"):
            d_own = np.where(own_p > 0, own_d / own_p, 0.0)
            d_fr = np.where(fr_p > 0, fr_d / fr_p, 0.0)
            ratio = np.where(d_fr > 0, d_own / d_fr, np.inf)
        return np.where(np.asarray(b.prolong.sum(axis=0)).ravel()[:n_e] > 0, ratio, np.nan)

    def seen_basis(self, included, fine_sight, min_own_sight: float | None = None) -> "HatBasis":
        """:meth:`basis` for the ``included`` elements less those whose own faces the camera
        hardly sees (:meth:`own_sight` below ``min_own_sight``, default :data:`OWN_SIGHT_MIN`);
        their vertices shared with the rest keep unknowns of their own (rim vertices), as on
        vertices.

        An element unknown is constant over the element's inner vertices, so its value,
        pinned by the light the camera sees at the vertices it shares with seen neighbours,
        is spread over its whole area. Where its own faces are hidden (demo-rig's captured
        surface: the flat underside that closes it on the stage, seen by the grazing edge of
        a pose at 1/200 of a side element's sensitivity) that is an extrapolation the data
        never see, and with λ small (the joint solve of two poses) it put 6 % of the total
        there. A rim vertex's light stays within one face of what the camera sees."""
        kappa = OWN_SIGHT_MIN if min_own_sight is None else float(min_own_sight)
        inc = np.ones(self.share.shape[1], bool) if included is None else np.array(included, bool)
        b = self.basis(inc)
        if self.to_fine is None or self.fine_to_elements is None:
            return b
        for _ in range(8):  # dropping an element only raises its neighbours' own sight: a few passes
            drop = inc & (self.own_sight(b, fine_sight) < kappa)
            if not drop.any():
                break
            inc &= ~drop
            b = self.basis(inc)
        return b

    def basis(self, included=None) -> "HatBasis":
        """The unknowns for the elements ``included`` (bool (n_elements,); None: all)."""
        import scipy.sparse as sp

        n_v, n_e = self.share.shape
        inc = np.ones(n_e, bool) if included is None else np.asarray(included, bool)
        Q = sp.csr_array(self.share @ sp.diags_array(inc.astype(np.float64)))
        inside = np.asarray(Q.sum(axis=1)).ravel()  # share of each vertex's hat on included elements
        outside = np.asarray(self.share.sum(axis=1)).ravel() - inside
        rim = (inside > 0) & ((outside > 1e-12) | self.on_boundary)
        scale = np.where((inside > 0) & ~rim, 1.0 / np.where(inside > 0, inside, 1.0), 0.0)
        Q = sp.csr_array(sp.diags_array(scale) @ Q)
        rim_idx = np.flatnonzero(rim)
        E = sp.csr_array((np.ones(rim_idx.size), (rim_idx, np.arange(rim_idx.size))), shape=(n_v, rim_idx.size))
        Q = sp.csr_array(sp.hstack([Q, E]))  # J = Q x, x exitance per unknown (photons mm⁻²)
        areas = np.concatenate([self.areas_mm2, self.vertex_areas_mm2[rim_idx]])
        inv = np.divide(1.0, areas, out=np.zeros_like(areas), where=areas > 0)
        P = sp.csr_array(sp.diags_array(self.vertex_areas_mm2) @ Q @ sp.diags_array(inv))
        Lc = sp.csr_array(Q.T @ self.laplacian @ Q)
        W = sp.csr_array(-(Lc - sp.diags_array(Lc.diagonal())))
        W.data = np.maximum(W.data, 0.0)
        W.eliminate_zeros()
        return HatBasis(P, sp.csr_array(self.vertex_to_elements @ P), areas, W, rim_idx)


@dataclass(frozen=True)
class HatBasis:
    """The unknowns of :meth:`ElementHats.basis`: the elements, then the rim vertices.

    Attributes
    ----------
    prolong : sparse (n_vertices, n_unknowns) ≥ 0, vertex lumped power per photon of each
        unknown (T of the unknowns = T per vertex @ prolong).
    to_elements : sparse (n_elements, n_unknowns), element power per photon of each unknown.
    areas_mm2 : (n_unknowns,) the unknown's exitance is its power over this area.
    stiffness : sparse (n_unknowns, n_unknowns) ≥ 0, the edge weights of ``∫|∇J|² dS``.
    rim_vertices : (n_rim,) the vertex of each unknown after the elements.
    """

    prolong: object
    to_elements: object
    areas_mm2: np.ndarray
    stiffness: object
    rim_vertices: np.ndarray


def cotangent_weights(vertices_mm: np.ndarray, faces: np.ndarray):
    """Edge weights ``w_ij = (cot α_ij + cot β_ij)/2`` (α, β the angles opposite edge ij)
    as a symmetric sparse (n, n) matrix, negative weights set to 0.

    For J linear on each triangle, ``∫|∇J|² dS = Σ_edges w_ij (J_i − J_j)²`` exactly (the
    P1 finite-element stiffness matrix is ``diag(W1) − W``): a smoothness prior that
    measures the exitance's gradient, not the mesh's connectivity. A graph Laplacian with
    unit weights also smooths along the diagonals of split quads and ignores how long an
    edge is. Weights of obtuse triangles can be negative; they are clipped at 0 (the prior
    must stay positive semi-definite), which changes nothing on meshes without them; a
    vertex left with no weight at all keeps its edges at the median weight.
    """
    import scipy.sparse as sp

    P = np.asarray(vertices_mm, dtype=np.float64)[faces]  # (F, 3, 3)
    rows, cols, w = [], [], []
    for k in range(3):  # the angle at corner k faces the edge (k+1, k+2)
        i, j = (k + 1) % 3, (k + 2) % 3
        u, v = P[:, i] - P[:, k], P[:, j] - P[:, k]
        sin = np.linalg.norm(np.cross(u, v), axis=1)
        cot = np.divide(np.einsum("ij,ij->i", u, v), sin, out=np.zeros(len(sin)), where=sin > 0)
        rows.append(faces[:, i]), cols.append(faces[:, j]), w.append(0.5 * cot)
    n = len(vertices_mm)
    W = sp.coo_array((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    W = sp.csr_array(W + W.T)
    W.data = np.maximum(W.data, 0.0)
    W.eliminate_zeros()
    lone = np.flatnonzero((np.asarray(W.sum(axis=1)).ravel() == 0) & np.isin(np.arange(n), faces))
    if lone.size and W.nnz:  # a vertex whose every angle is obtuse-clipped: tie it to its neighbours anyway
        e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        e = e[np.isin(e, lone).any(axis=1)]
        fill = sp.coo_array((np.full(len(e), float(np.median(W.data))), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        fill = sp.csr_array(((fill + fill.T) > 0).astype(np.float64) * float(np.median(W.data)))
        W = sp.csr_array(W.maximum(fill))
    return W


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric coordinates of points p (n, 3) in triangles tri (n, 3, 3)."""
    e0, e1, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((e0, e0), (e0, e1), (e1, e1)))
    d20, d21 = np.einsum("ij,ij->i", d, e0), np.einsum("ij,ij->i", d, e1)
    den = d00 * d11 - d01 ** 2
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=1)


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """How many faces use each distinct (undirected) edge of a triangle list (F, 3)."""
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def merge(*surfaces: Surface) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate surfaces into one (vertices, faces) triangle soup for occlusion."""
    verts, faces, off = [], [], 0
    for s in surfaces:
        verts.append(s.vertices_mm)
        faces.append(s.faces + off)
        off += len(s.vertices_mm)
    return np.concatenate(verts), np.concatenate(faces)


def box(lo_mm: np.ndarray, hi_mm: np.ndarray) -> Surface:
    """An axis-aligned closed box (occluder only: no elements), outward winding."""
    lo, hi = np.asarray(lo_mm, float), np.asarray(hi_mm, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return Surface(v, f, -np.ones(len(f), np.int64), 0)


def rectangle(center_mm, axis_u, axis_v, size_mm) -> Surface:
    """A flat rectangle (two triangles, occluder only), normal = axis_u x axis_v."""
    c, u, w = (np.asarray(x, float) for x in (center_mm, axis_u, axis_v))
    a, b = size_mm[0] / 2, size_mm[1] / 2
    v = np.array([c - a * u - b * w, c + a * u - b * w, c + a * u + b * w, c - a * u + b * w])
    return Surface(v, np.array([[0, 1, 2], [0, 2, 3]]), -np.ones(2, np.int64), 0)


def read_mesh(path: Path, *, scale_to_mm: float = 1.0) -> Surface:
    """Read a mesh file and validate it (see :func:`read_mesh_checked`); the notes are dropped."""
    return read_mesh_checked(path, scale_to_mm=scale_to_mm)[0]


def read_mesh_checked(path: Path, *, scale_to_mm: float = 1.0) -> tuple[Surface, list[str]]:
    """Read any mesh pyvista reads (PLY through plyfile, so face properties survive) and
    validate it with :func:`validated`.

    Each triangle is an element unless the file has an integer face property (PLY) or
    cell array (VTK) ``element``; a polygon's triangles share its element.

    Returns
    -------
    surface : Surface
    notes : list of str
        What the file yielded (triangles, elements) and what was repaired.

    Raises
    ------
    ValueError
        Naming the file: unreadable, empty, non-finite coordinates, face indices out of range,
        elements of zero area, or inconsistent winding that cannot be repaired.
    """
    path = Path(path)
    if path.suffix.lower() == ".ply":
        verts, faces, element, how = _read_ply(path)
    else:
        verts, faces, element, how = _read_pyvista(path)
    verts = verts * scale_to_mm
    if element is not None:
        ids, elem = np.unique(element, return_inverse=True)
        surf, notes = validated(verts, faces, elem.ravel(), len(ids), name=str(path), element_ids=ids)
    else:
        surf, notes = validated(verts, faces, np.arange(len(faces)), len(faces), name=str(path))
    notes.insert(0, f"mesh {path.name}: {len(surf.faces)} triangles, {surf.n_elements} elements ({how})")
    return surf, notes


def _read_ply(path: Path):
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        f = ply["face"]
    except Exception as e:  # plyfile raises several kinds for malformed files
        raise ValueError(f"mesh file {path} cannot be read as PLY: {e}") from None
    try:
        verts = np.column_stack([np.asarray(v[c], np.float64) for c in ("x", "y", "z")])
    except (ValueError, KeyError) as e:
        raise ValueError(f"mesh file {path}: vertices lack x, y, z ({e})") from None
    names = [p.name for p in f.properties]
    lists = "vertex_indices" if "vertex_indices" in names else "vertex_index" if "vertex_index" in names else None
    if lists is None or len(f.data) == 0 or len(verts) == 0:
        raise ValueError(f"mesh file {path} holds no surface triangles")
    polys = f.data[lists]
    element, how = None, "one per triangle"
    key = _element_key(names)
    if key is not None:
        raw = np.asarray(f.data[key])
        element = element_ids_of(raw, f"mesh file {path}: face property {key!r}")
        how = _element_how("face property", key, raw.dtype)
    tris, owner = [], []
    for k, poly in enumerate(polys):
        poly = np.asarray(poly, np.int64)
        if len(poly) < 3:
            raise ValueError(f"mesh file {path}: face {k} has {len(poly)} vertex index(es); a face needs 3 or more")
        for j in range(1, len(poly) - 1):  # fan: a polygon's triangles keep its element
            tris.append((poly[0], poly[j], poly[j + 1]))
            owner.append(k)
    faces = np.array(tris, np.int64)
    return verts, faces, (element[np.array(owner)] if element is not None else None), how


def _read_pyvista(path: Path):
    import pyvista as pv

    try:
        mesh = pv.read(str(path))
    except Exception as e:  # pyvista raises many kinds; all mean "cannot read"
        raise ValueError(f"mesh file {path} cannot be read: {e}") from None
    if isinstance(mesh, pv.MultiBlock):
        mesh = mesh.combine()
    mesh = mesh.extract_surface(algorithm=None) if not isinstance(mesh, pv.PolyData) else mesh
    if mesh.n_cells == 0 or mesh.n_points == 0:
        raise ValueError(f"mesh file {path} holds no surface triangles")
    key = _element_key(list(mesh.cell_data.keys()))
    if key is not None:
        dtype = np.asarray(mesh.cell_data[key]).dtype
        mesh.cell_data["_element"] = element_ids_of(np.asarray(mesh.cell_data[key]),
                                                    f"mesh file {path}: cell array {key!r}")
    tri = mesh.triangulate()
    faces = tri.faces.reshape(-1, 4)[:, 1:]
    if len(faces) == 0:
        raise ValueError(f"mesh file {path} holds no surface triangles")
    verts = np.asarray(tri.points, dtype=np.float64)
    if key is not None:
        return verts, faces, np.asarray(tri.cell_data["_element"]).ravel(), _element_how("cell array", key, dtype)
    return verts, faces, None, "one per triangle"


# what a mesh file may call the array that groups its faces into elements (the first found, in
# this order; case does not matter): DESIGN's 'element', and the names other tools write
ELEMENT_NAMES = ("element", "elements", "element_id", "element_ids", "elementid")


def _element_key(names) -> str | None:
    """The face property / cell array that holds each face's element, if the file has one."""
    lower = {str(n).lower(): n for n in reversed(list(names))}
    return next((lower[k] for k in ELEMENT_NAMES if k in lower), None)


def _element_how(kind: str, key: str, dtype) -> str:
    if np.issubdtype(dtype, np.integer):
        return f"from its integer {kind} {key!r}"
    return f"from its {kind} {key!r} (whole numbers stored as {dtype})"


def element_ids_of(values: np.ndarray, what: str) -> np.ndarray:
    """A file's element ids as int64: integers, or floating-point numbers that are whole (as
    MATLAB and many writers store them); ValueError naming ``what`` for anything else (a
    fraction, NaN, more than one component per face), rather than a silent one-per-triangle."""
    v = np.asarray(values)
    if v.ndim > 1 and v.shape[1:] != (1,) * (v.ndim - 1):
        raise ValueError(f"{what} has {int(np.prod(v.shape[1:]))} components per face; it must hold one "
                         "element id per face")
    v = v.reshape(len(v))
    if np.issubdtype(v.dtype, np.integer):
        return v.astype(np.int64)
    if not (np.issubdtype(v.dtype, np.floating) or v.dtype == bool):
        raise ValueError(f"{what} holds {v.dtype} values; it must hold an integer element id per face")
    bad = ~np.isfinite(v) | (v != np.round(v)) | (np.abs(v) > 2.0**53)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{what} must hold whole-number element ids; face {k} has {v[k].item()!r} "
                         f"({int(bad.sum())} face(s) like it)")
    return v.astype(np.int64)


def validated(vertices_mm, faces, element_of_face, n_elements: int, *, name: str = "the mesh",
              element_ids=None) -> tuple[Surface, list[str]]:
    """Check a triangle mesh and repair what can be repaired without guessing.

    Refused (ValueError naming ``name``): non-finite coordinates, face indices outside the
    vertex list, an element whose faces all have zero area.  Repaired with a note: faces of
    zero area are dropped; an inconsistent winding is made consistent (faces flipped to
    agree with their neighbours); a closed surface wound inward is turned outward.
    """
    v = np.asarray(vertices_mm, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    eof = np.asarray(element_of_face, np.int64)
    notes: list[str] = []
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} vertex(es) have non-finite coordinates (first: vertex "
                         f"{int(np.argmax(bad))}: {v[np.argmax(bad)].tolist()})")
    from ..config import MAX_LENGTH_MM

    far = np.abs(v).max(axis=1, initial=0.0) > MAX_LENGTH_MM if v.ndim == 2 and len(v) else np.zeros(0, bool)
    if far.any():
        k = int(np.argmax(far))
        raise ValueError(f"{name}: vertex {k} lies at {v[k].tolist()} mm, more than 1 km from the origin "
                         f"({int(far.sum())} vertex(es) like it); coordinates are millimetres and at most "
                         f"{MAX_LENGTH_MM:g} mm (a mesh in micrometres needs scale_to_mm)")
    if len(f) == 0:
        raise ValueError(f"{name} holds no surface triangles")
    if eof.shape != (len(f),):
        raise ValueError(f"{name}: {eof.size} element number(s) for {len(f)} faces; each face needs one")
    if n_elements < 1 or eof.max() >= n_elements or eof.min() < -1:
        raise ValueError(f"{name}: its faces name elements {int(eof.min())} to {int(eof.max())}, but it has "
                         f"{n_elements} element(s) (numbered 0 to {n_elements - 1}; -1: a face of no element)")
    if element_ids is not None and len(element_ids) != n_elements:
        raise ValueError(f"{name}: {len(element_ids)} element id(s) for {n_elements} elements")
    out = (f < 0) | (f >= len(v))
    if out.any():
        k = int(np.argmax(out.any(axis=1)))
        raise ValueError(f"{name}: face {k} uses vertex index {int(f[k][out[k]][0])}, but there are only "
                         f"{len(v)} vertices (indices 0 to {len(v) - 1})")
    scale = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
    v, f, merged = _welded(v, f, WELD_RELATIVE * scale)
    if merged:
        notes.append(f"{name}: {merged} vertex(es) repeated at the same place (as STL exports and some writers "
                     "store a mesh, each face with its own corners) were merged, so that faces that meet share "
                     "their corners")
    t = v[f]
    area = triangle_areas(t)
    degenerate = (area <= 1e-12 * max(scale, 1e-300) ** 2) | (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if degenerate.any():
        keep_area = np.bincount(eof[~degenerate & (eof >= 0)], weights=area[~degenerate & (eof >= 0)],
                                minlength=n_elements)
        empty = np.flatnonzero(keep_area <= 0)
        if len(empty):
            label = element_ids[empty[0]] if element_ids is not None else empty[0]
            raise ValueError(f"{name}: element {label} has zero area (all its faces are degenerate); "
                             f"{len(empty)} element(s) like it. An element of zero area would get an infinite exitance")
        notes.append(f"{name}: dropped {int(degenerate.sum())} face(s) of zero area")
        f, eof = f[~degenerate], eof[~degenerate]
    try:
        f, flipped = _consistent_winding(f)
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None
    if flipped:
        notes.append(f"{name}: {flipped} face(s) were wound against their neighbours and were flipped")
    counts = edge_face_counts(f)
    if np.all(counts == 2):
        t = v[f]
        volume = float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)
        if volume < 0:
            f = f[:, ::-1].copy()
            notes.append(f"{name}: the closed surface was wound inward (its faces' normals pointed into the subject); "
                         "all faces were flipped to face outward")
    return Surface(v, f, eof, n_elements, element_ids), notes


# Vertices closer than this fraction of the mesh's size are one vertex (float32 rounding of a
# 100-mm mesh is ~1e-7 of it; real features are ~1e-3 of it or more)
WELD_RELATIVE = 1e-6


def _welded(v: np.ndarray, f: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Merge the vertices that faces use which lie within ``tol`` of each other (each group to its
    first vertex; the vertices no face uses then are dropped); returns (vertices, faces, how many
    were merged).  A mesh whose faces each have
    their own corners is otherwise a heap of loose triangles: no vertex is shared, so neither the
    surface's closedness, its winding nor an exitance continuous across faces can be seen."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    used = np.unique(f)
    if len(used) < 2:
        return v, f, 0
    pairs = cKDTree(v[used]).query_pairs(max(tol, 0.0), output_type="ndarray")
    if len(pairs) == 0:
        return v, f, 0
    n = len(used)
    _, label = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
                                    directed=False)
    first = np.full(label.max() + 1, n)
    np.minimum.at(first, label, np.arange(n))
    to = np.arange(len(v))
    to[used] = used[first[label]]
    f = to[f]
    keep = np.unique(f)  # the merged-away copies are no vertex of any face: drop them
    index = np.full(len(v), -1)
    index[keep] = np.arange(len(keep))
    return v[keep], index[f], int(n - (label.max() + 1))


def _consistent_winding(faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Flip faces so that every edge shared by two faces runs opposite ways in them (the
    first face of each connected piece keeps its winding); returns faces and how many flipped."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, counts = np.unique(directed, axis=0, return_counts=True)
    if np.all(counts == 1):
        return faces, 0
    n = len(faces)
    und = np.sort(directed, axis=1)
    key = und[:, 0] * (int(und.max()) + 1) + und[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    ends = np.r_[starts[1:], len(ks)]
    neighbours: list[list[tuple[int, bool]]] = [[] for _ in range(n)]
    for s0, e0 in zip(starts, ends):
        if e0 - s0 != 2:  # boundary or non-manifold edge: no constraint
            continue
        a, b = order[s0], order[s0 + 1]
        fa, fb = a // 3, b // 3
        same = bool(np.all(directed[a] == directed[b]))  # same direction: one of the two must flip
        neighbours[fa].append((fb, same))
        neighbours[fb].append((fa, same))
    flip = np.zeros(n, bool)
    seen = np.zeros(n, bool)
    for root in range(n):
        if seen[root]:
            continue
        seen[root] = True
        stack = [root]
        while stack:
            x = stack.pop()
            for y, same in neighbours[x]:
                want = flip[x] ^ same
                if not seen[y]:
                    seen[y] = True
                    flip[y] = want
                    stack.append(y)
                elif flip[y] != want:
                    raise ValueError("the mesh cannot be wound consistently (a Moebius-like surface or "
                                     "faces that touch inconsistently)")
    out = faces.copy()
    out[flip] = out[flip][:, ::-1]
    return out, int(flip.sum())
