"""The unknowns of a solve: elements, sub-elements, vertices or linear elements.

:func:`resolve_unknowns` is the rule ``unknowns: auto`` follows; :class:`Grid` holds a run's
T per pose on those unknowns; :class:`ElementMap` / :class:`VertexMap` share vertex unknowns
out to the elements; :func:`element_unknowns` makes the ``linear_elements`` basis of one
solve and :func:`on_elements` classifies a vertex solve per element.  Method settings are
any object with ``method`` and ``unknowns`` and a pydantic ``model_copy``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

@dataclass
class Grid:
    """The unknowns of a solve: the elements, or sub-elements summed back per element, or
    vertices (exitance linear within a face) shared out to the elements."""

    Ts: list  # per pose, (n_pixels, n_unknowns)
    adjacency: sp.csr_matrix  # unknowns touching, as edge weights of the smooth prior (vertices: cotangent)
    parent: np.ndarray | None  # unknown -> element; None when the unknowns are the elements
    n_elements: int
    areas: np.ndarray | None = None  # (n_unknowns,) mm²: priors act on exitance
    surface: object = None  # the elements' surface
    paths: list | None = None  # per pose, the T cache file Ts[k] was read from (vertices: the fine T)
    vmap: "VertexMap | None" = None  # vertices: how the fine T gives T per vertex and per element
    maps: list | None = None  # vertices: per pose the ElementMap (parent is then None)
    curvature: object = None  # the emission's curvature term: inverse.curvature.CurvaturePass (None: off)

    def parts(self, k: int | None = None):
        """What run_method takes as ``parent`` for pose k (None: all poses jointly)."""
        if self.maps is None:
            return self.parent
        if k is not None:
            return self.maps[k]
        m = self.maps[0]
        return replace(m, T=sp.vstack([x.T for x in self.maps]).tocsr(),
                       T_fine=None if m.T_fine is None else sp.vstack([x.T_fine for x in self.maps]).tocsr())


@dataclass
class ElementMap:
    """Unknowns that are not parts of one element (vertices): the element power per unit of
    each unknown, and the element-level T, adjacency and areas that classify the elements
    (observed, poorly observed) exactly as a solve per element would."""

    to_elements: sp.csr_array  # (n_elements, n_unknowns)
    T: sp.csr_array  # (n_pixels, n_elements)
    adjacency: sp.csr_matrix
    areas: np.ndarray
    hats: object = None  # linear_elements: the T given is per vertex; run_method makes the element unknowns
    T_fine: object = None  # linear_elements: (n_pixels, n_fine) T per face of the refined surface (what each face is seen)


@dataclass
class VertexMap:
    """Pose-independent maps of the vertex unknowns (no T inside: a sweep task takes this
    and the fine T's cache path): T per vertex = T_fine · to_fine, per element = T_fine ·
    fine_to_elements."""

    to_fine: sp.csr_array  # (n_fine, n_vertices)
    fine_to_elements: sp.csr_array  # (n_fine, n_elements)
    to_elements: sp.csr_array  # (n_elements, n_vertices)
    adjacency: sp.csr_matrix  # elements touching
    areas: np.ndarray  # element areas, mm²
    hats: object = None  # linear_elements: surface.ElementHats (one unknown per element, from the vertices' T)
    # the emission's tangential-flux term (optics.emission.tangent_operator), (2 n_fine, n_vertices); None: none
    tangent: "sp.csr_array | None" = None

    def unknowns_T(self, T_fine, T_tangent=None) -> sp.csr_array:
        """T per vertex (columns of the hat functions; linear_elements: run_method combines them);
        with the fine T's tangential matrix (pixels x 2 n_fine) also the light the exitance
        gradient of each hat function tilts into each pixel.  A hat alone is not an exitance the
        term holds for everywhere: at its rim phi_v -> 0 while its gradient does not, and a pixel
        that sees only that rim at a grazing angle can get a negative entry.  The solvers need
        T >= 0, so such entries are set to 0 and the rest of the column is scaled back to the
        column's own sum: the term tilts a hat's light between pixels but does not add to it, and
        clipping alone would (2.4-3.1 % of T's mass at 45-60 deg on issue 21's box, 2-mm elements
        seen through 0.7-mm pixels), reading every oblique total that much too low."""
        if T_tangent is None or self.tangent is None:
            return sp.csr_array(T_fine @ self.to_fine)
        T = sp.csr_array(T_fine @ self.to_fine + T_tangent @ self.tangent)
        signed = np.asarray(T.sum(axis=0)).ravel()
        np.maximum(T.data, 0.0, out=T.data)
        clipped = np.asarray(T.sum(axis=0)).ravel()
        keep = np.divide(np.maximum(signed, 0.0), clipped, out=np.ones_like(clipped), where=clipped > 0)
        T = sp.csr_array(T @ sp.diags_array(keep))
        T.eliminate_zeros()
        return T

    def element_map(self, T_fine) -> ElementMap:
        return ElementMap(self.to_elements, sp.csr_array(T_fine @ self.fine_to_elements), self.adjacency, self.areas,
                          self.hats, None if self.hats is None else sp.csr_array(T_fine))



MAX_AUTO_SUB_ELEMENTS = 6000  # dense solves: 6000² doubles is 0.29 GB a matrix (a 5880-vertex pose took 14 s)


def resolve_unknowns(m, surface, camera=None):
    """``unknowns: auto``: ``smooth`` solves for the exitance at the vertices (linear within
    each face, continuous across edges; :meth:`Surface.vertex_basis`) and shares it out to
    the elements when there are at most EXACT_MAX_UNKNOWNS vertices, beyond on one unknown per
    element with the exitance still linear within faces (``linear_elements``, up to
    MAX_AUTO_SUB_ELEMENTS elements); the other methods, and larger meshes, solve per element. (``camera`` is kept in the signature for its
    callers: how finely the camera resolves an element no longer decides, see below.)

    Light varies within an element, and where it varies steeply a model constant per element
    (or per face) cannot fit the data even without noise: honest simulations of a cylinder
    at 21 pixels per element, noiseless, λ → 0, give χ²/pixel (at SNR 30) 3.7 per element and
    2.8 per face with the source at the limb (2.2 % / 2.8 % error), and 1.7 / 1.2 with the
    source behind (8 % / 13 % error, totals over well-observed elements 0.96 / 0.93), against
    0.06 / 0.04 (0.3 % / 0.6 %, 1.000 / 1.002) for exitance linear in each face, with fewer
    unknowns (312 vertices, 576 faces). At 5–6 pixels per element (paper-3d, heights, the
    demo) it helps as much: 3.13 → 1.40 %, 3.19 → 2.46 %, 5.0 → 2.1 % error.

    Until November 2026 ``auto`` also asked for ≥ 12 pixels per element (≥ 4 where there are
    at most 1.25 vertices per element) and at most 4000 vertices, from one scene at 0.6
    pixels per element whose total went 1.038 → 1.067 on vertices. Measured since, on the
    independent renderer's cylinder (elements of 2 x 2 quads, SNR 30, blob 20° / 45° from
    the top; error over observed elements, per element → vertices): 48 x 24 quads at 4.7
    pixels per element 7.5 → 2.7 % / 10.0 → 4.3 %, at 2 pixels 9.9 → 5.5 % / 16.1 → 9.2 %, at
    0.9 pixels 8.8 → 5.3 % / 11.6 → 6.0 %; 96 x 48 quads (4706 vertices) at 4.7 pixels
    3.2 → 2.0 % / 4.3 → 2.6 %, at 0.2 pixels 6.2 → 5.4 % / 8.8 → 6.5 %; the battery's
    cylinder at 2.2 and 0.55 pixels per element 6.1 → 3.7 % and 7.4 → 5.0 % (top), 9.3 →
    6.3 % and 12.9 → 8.4 % (limb). Vertices won every one; totals moved either way by ≤ 1.5 %.

    Beyond :data:`~fluxcli.inverse.methods.EXACT_MAX_UNKNOWNS` vertices (where the exact
    non-negative steps would cost minutes) ``auto`` solves on ``linear_elements`` instead: one
    unknown per element (and per vertex on the rim of what the camera sees), the exitance
    still linear within faces (:class:`~fluxcli.surface.mesh.ElementHats`), so the reported
    elements, not the mesh, set the cost and the solve stays exact. Issue 25's scene (5666
    vertices, 1168 elements, 2 x 2 quads per element) went from minutes to seconds; at SNR 30
    the element-sized basis tied or won on the battery's grouped-quad cases (renderer-direct
    1.55 → 1.38 %, indep-direct 1.22 → 1.16 %, indep-mirrors 1.11 → 1.03 %). It has a quarter
    of the vertices' freedom, and where the light rises steeply within elements and the data
    are nearly noiseless the vertices win (test_independent_renderer's source behind the
    limb at SNR 300: 0.4 % on vertices, 1.8 % per element), so below the cap vertices stay
    (and the battery's figures with them)."""
    if m.unknowns != "auto":
        return m
    if m.method != "smooth":
        return m.model_copy(update={"unknowns": "elements"})
    from ..inverse.methods import EXACT_MAX_UNKNOWNS

    nv = n_vertices(surface)
    if nv <= EXACT_MAX_UNKNOWNS:
        return m.model_copy(update={"unknowns": "vertices"})
    return m.model_copy(update={"unknowns": "linear_elements" if surface.n_elements <= MAX_AUTO_SUB_ELEMENTS
                                else "elements"})


def n_vertices(surface) -> int:
    """Unknowns of ``reconstruct.unknowns: vertices``: the vertices of the element faces."""
    return int(np.unique(surface.faces[surface.element_of_face >= 0]).size)



def element_unknowns(T_vertices, valid, emap: ElementMap):
    """``unknowns: linear_elements``: T per vertex -> T per unknown (the elements these pixels
    see, and the vertices on the rim of that set: :class:`~fluxcli.surface.mesh.ElementHats`);
    returns that T, the ElementMap sharing the unknowns out to the elements, the prior's
    edge weights and the unknowns' areas (mm²)."""
    from ..inverse._common import DEFAULT_REL_THRESHOLD, observed

    hats = emap.hats
    keep = np.asarray(valid).ravel()
    included = observed(sp.csr_array(emap.T[keep]), DEFAULT_REL_THRESHOLD)  # the elements' own T
    if emap.T_fine is None:
        b = hats.basis(included)
    else:  # less the elements the camera sees only the edges of (ElementHats.seen_basis)
        b = hats.seen_basis(included, np.asarray(sp.csr_array(emap.T_fine[keep]).sum(axis=0)).ravel())
    return (sp.csr_array(T_vertices @ b.prolong), replace(emap, to_elements=b.to_elements, hats=None, T_fine=None),
            b.stiffness, b.areas_mm2)


def on_elements(res, keep, emap: ElementMap):
    """A solve on vertex unknowns as element powers; the elements are classified on their
    own T (sensitivity, neighbours, σ of the element sums), as a solve per element would."""
    from ..inverse.methods import POOR_SHARE_TEXT, observation_classes, poor_share_warning
    from ..inverse._common import DEFAULT_REL_THRESHOLD

    T_el = emap.T[keep]
    power = emap.to_elements @ np.where(res.observed, res.power, 0.0)
    sigma = res.sigma_groups if res.sigma_groups is not None else np.full(power.size, np.nan)
    cls = observation_classes(T_el, power, sigma, adjacency=emap.adjacency, areas=emap.areas,
                              rel_threshold=DEFAULT_REL_THRESHOLD)
    observed = cls > 0
    warnings = [w for w in res.warnings if POOR_SHARE_TEXT not in w]
    poor = poor_share_warning(power, observed, cls)
    if poor:
        warnings.append(poor)
    return replace(res, power=np.where(observed, power, np.nan), observed=observed,
                   sigma=np.where(observed, sigma, np.nan), observation=cls, warnings=tuple(warnings))
