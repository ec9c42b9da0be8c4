"""Phantom surface generators, built in their own frame (centred at the origin).

Each returns the surface and its own rotation axis (a point and a unit direction).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import Surface


@dataclass(frozen=True)
class RoundBody:
    """The curved surface a round phantom's vertices lie on, in its own frame (centred at the
    origin): a cylinder or band of ``radius_mm`` about coordinate axis ``axis`` (0: x, 1: y), or
    a sphere (``axis`` None). Its flat facets are chords of it; :meth:`Surface.subdivided` moves
    the midpoints it makes onto it, so finer faces follow the body the light leaves (a Monte
    Carlo truth is transported through the round body itself, ``fluxcli.montecarlo``)."""

    radius_mm: float
    axis: int | None = None

    def _rho(self, p_mm: np.ndarray) -> np.ndarray:
        q = np.array(p_mm, float)
        if self.axis is not None:
            q[:, self.axis] = 0.0
        return np.linalg.norm(q, axis=1)

    def holds(self, p_mm: np.ndarray) -> np.ndarray:
        """Which points lie on the curved surface (to 1e-7 of its radius)."""
        return np.abs(self._rho(p_mm) - self.radius_mm) <= 1e-7 * self.radius_mm

    def project(self, p_mm: np.ndarray) -> np.ndarray:
        """The points moved straight out from the axis (the centre) onto the surface."""
        p = np.asarray(p_mm, float)
        q = p * (self.radius_mm / self._rho(p))[:, None]
        if self.axis is not None:
            q[:, self.axis] = p[:, self.axis]
        return q


def _grid_quads(n_a: int, n_b: int, wrap_a: bool) -> np.ndarray:
    """Quads (i, j) -> four vertex indices on an (n_a(+1)) x (n_b+1) vertex grid."""
    na_v = n_a if wrap_a else n_a + 1
    i, j = np.meshgrid(np.arange(n_a), np.arange(n_b), indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1 = (i + 1) % na_v if wrap_a else i + 1
    return np.stack([j * na_v + i, j * na_v + i1, (j + 1) * na_v + i1, (j + 1) * na_v + i], axis=1)


def _split(quads: np.ndarray, elements: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return faces, np.concatenate([elements, elements])


def cylinder(*, radius_mm: float, length_mm: float, n_angular: int, n_axial: int,
             cap_elements: bool = False) -> tuple[Surface, np.ndarray, np.ndarray]:
    """Closed cylinder along x, centred at the origin.

    Side elements are numbered ``j = i_angular * n_axial + i_axial``; element
    ``i_angular = 0`` starts at the top (+z) and the angle runs from +z towards +y.
    Caps are occluders unless ``cap_elements`` (then one element each, after the side).
    """
    phi = 2 * np.pi * np.arange(n_angular) / n_angular
    x = np.linspace(-length_mm / 2, length_mm / 2, n_axial + 1)
    ring = np.stack([np.sin(phi), np.cos(phi)], axis=1) * radius_mm  # (y, z)
    side_v = np.array([[xi, y, z] for xi in x for y, z in ring])
    quads = _grid_quads(n_angular, n_axial, wrap_a=True)
    faces, elem = _split(quads, np.arange(n_angular * n_axial))
    n_side = len(side_v)
    centres = np.array([[-length_mm / 2, 0, 0], [length_mm / 2, 0, 0]])
    verts = np.concatenate([side_v, centres])
    cap_faces, cap_elem = [], []
    for k, (xi, sign) in enumerate(((0, -1), (n_axial, 1))):
        c = n_side + k
        a = xi * n_angular + np.arange(n_angular)
        b = xi * n_angular + (np.arange(n_angular) + 1) % n_angular
        f = np.stack([np.full(n_angular, c), a, b], axis=1)
        if sign < 0:
            f = f[:, ::-1]
        cap_faces.append(f)
        cap_elem.append(np.full(n_angular, n_angular * n_axial + k if cap_elements else -1))
    faces = np.concatenate([faces, *cap_faces])
    elem = np.concatenate([elem, *cap_elem])
    n_el = n_angular * n_axial + (2 if cap_elements else 0)
    surf = _orient_outward(Surface(verts, faces, elem, n_el), np.zeros(3))
    return surf, np.zeros(3), np.array([1.0, 0, 0])


def box(*, size_mm, element_mm: float) -> tuple[Surface, np.ndarray, np.ndarray]:
    """Closed box centred at the origin, sides ``size_mm`` along x, y, z; each face split into a
    grid of ``round(side / element_mm)`` elements per side (two triangles each). Turns about x."""
    size = np.asarray(size_mm, float)
    verts, faces, elem = [], [], []
    n_v = n_el = 0
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        na, nb = (max(1, int(round(size[k] / element_mm))) for k in (a, b))
        ua = np.linspace(-size[a] / 2, size[a] / 2, na + 1)
        ub = np.linspace(-size[b] / 2, size[b] / 2, nb + 1)
        for sign in (-1.0, 1.0):
            v = np.zeros(((na + 1) * (nb + 1), 3))
            gb, ga = np.meshgrid(ub, ua, indexing="ij")
            v[:, a], v[:, b], v[:, axis] = ga.ravel(), gb.ravel(), sign * size[axis] / 2
            f, e = _split(_grid_quads(na, nb, wrap_a=False), n_el + np.arange(na * nb))
            verts.append(v)
            faces.append(f + n_v)
            elem.append(e)
            n_v += len(v)
            n_el += na * nb
    # one vertex where the grids of two faces meet along an edge: a closed surface
    v_all = np.concatenate(verts)
    uniq, inv = np.unique(np.round(v_all, 9), axis=0, return_inverse=True)
    surf = Surface(uniq, inv.ravel()[np.concatenate(faces)], np.concatenate(elem), n_el)
    return _orient_outward(surf, np.zeros(3)), np.zeros(3), np.array([1.0, 0, 0])


def ring(*, radius_mm: float, thickness_mm: float, n_elements: int,
         strips_per_element: int = 1) -> tuple[Surface, np.ndarray, np.ndarray]:
    """The paper's 2-D slice: an open cylindrical band of ``n_elements`` around the y axis.

    Element 0 is centred on the top (+z) and faces straight up; angles run towards +x.
    Each element is made of ``strips_per_element`` strips along the arc (its sub-elements,
    the paper's "9x in a single direction").
    """
    n_strips = n_elements * strips_per_element
    phi = 2 * np.pi * (np.arange(n_strips) / strips_per_element - 0.5) / n_elements
    y = np.array([-thickness_mm / 2, thickness_mm / 2])
    verts = np.array([[radius_mm * np.sin(p), yi, radius_mm * np.cos(p)] for yi in y for p in phi])
    quads = _grid_quads(n_strips, 1, wrap_a=True)
    faces, strip = _split(quads, np.arange(n_strips))
    surf = Surface(verts, faces, strip // strips_per_element, n_elements,
                   subelement_of_face=strip if strips_per_element > 1 else None)
    return _orient_outward(surf, np.zeros(3)), np.zeros(3), np.array([0.0, 1, 0])


def sphere(*, radius_mm: float, n_latitude: int, n_longitude: int) -> tuple[Surface, np.ndarray, np.ndarray]:
    """Closed UV sphere at the origin; each latitude x longitude cell one element."""
    theta = np.linspace(0, np.pi, n_latitude + 1)[1:-1]
    phi = 2 * np.pi * np.arange(n_longitude) / n_longitude
    body = np.array([[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)] for t in theta for p in phi])
    verts = np.concatenate([[[0, 0, 1]], body, [[0, 0, -1]]]) * radius_mm
    faces, elem = [], []
    n_top, n_bot = 0, len(verts) - 1
    for k in range(n_longitude):
        k1 = (k + 1) % n_longitude
        faces.append((n_top, 1 + k, 1 + k1))
        elem.append(k)
    for r in range(n_latitude - 2):
        for k in range(n_longitude):
            k1 = (k + 1) % n_longitude
            a, b = 1 + r * n_longitude + k, 1 + r * n_longitude + k1
            c, d = a + n_longitude, b + n_longitude
            e = (r + 1) * n_longitude + k
            faces += [(a, c, d), (a, d, b)]
            elem += [e, e]
    last = 1 + (n_latitude - 2) * n_longitude
    for k in range(n_longitude):
        k1 = (k + 1) % n_longitude
        faces.append((n_bot, last + k1, last + k))
        elem.append((n_latitude - 1) * n_longitude + k)
    surf = Surface(verts, np.array(faces), np.array(elem), n_latitude * n_longitude)
    return _orient_outward(surf, np.zeros(3)), np.zeros(3), np.array([1.0, 0, 0])


def patch(*, size_mm: tuple[float, float], n: tuple[int, int], center_mm, normal) -> tuple[Surface, np.ndarray, np.ndarray]:
    """A flat rectangle of n[0] x n[1] elements facing ``normal``."""
    nrm = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(helper, nrm)
    u /= np.linalg.norm(u)
    w = np.cross(nrm, u)
    a = np.linspace(-size_mm[0] / 2, size_mm[0] / 2, n[0] + 1)
    b = np.linspace(-size_mm[1] / 2, size_mm[1] / 2, n[1] + 1)
    verts = np.array([np.asarray(center_mm, float) + ai * u + bi * w for bi in b for ai in a])
    quads = _grid_quads(n[0], n[1], wrap_a=False)
    faces, elem = _split(quads, np.arange(n[0] * n[1]))
    surf = Surface(verts, faces, elem, n[0] * n[1])
    if np.dot(surf.face_normals[0], nrm) < 0:
        surf = Surface(verts, faces[:, ::-1], elem, n[0] * n[1])
    return surf, np.asarray(center_mm, float), u


def _orient_outward(surf: Surface, centre: np.ndarray) -> Surface:
    """Wind every face to point away from ``centre`` (right for the convex phantoms here)."""
    c = surf.face_vertices_mm.mean(axis=1) - centre
    inward = np.einsum("ij,ij->i", surf.face_normals, c) < 0
    faces = np.where(inward[:, None], surf.faces[:, ::-1], surf.faces)
    return Surface(surf.vertices_mm, faces, surf.element_of_face, surf.n_elements,
                   subelement_of_face=surf.subelement_of_face)
