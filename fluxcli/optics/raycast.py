"""The one ray caster: segment visibility against a triangle scene with Embree (embreex).

Occlusion queries go through :mod:`fluxcli.optics.embree_native` (the same Embree library,
called from compiled code without the GIL); first-hit queries through embreex.
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh


class OcclusionScene:
    """Everything that can block light, as one Embree scene.

    Parameters
    ----------
    vertices_mm : (V, 3) float
    faces : (F, 3) int
    """

    def __init__(self, vertices_mm: np.ndarray, faces: np.ndarray):
        self._empty = len(faces) == 0
        self._vertices, self._faces = vertices_mm, faces
        self._native = None
        if not self._empty:
            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(self._scene, np.ascontiguousarray(vertices_mm, np.float32),
                         np.ascontiguousarray(faces, np.int32))

    @property
    def native(self):
        """The scene for compiled kernels (addresses of the scene and of Embree's occlusion
        functions); None for an empty scene."""
        if self._empty:
            return None
        if self._native is None:
            from . import embree_native  # numba: imported when occlusion is first asked for

            self._native = embree_native.NativeScene(self._vertices, self._faces)
        return self._native

    def blocked(self, origins_mm: np.ndarray, directions: np.ndarray, lengths_mm: np.ndarray) -> np.ndarray:
        """True where the segment origin + t*direction, 0 < t < length, hits a triangle.

        ``directions`` must be unit vectors; arrays of shape (n, 3), (n, 3), (n,).
        """
        n = len(origins_mm)
        out = np.zeros(n, bool)
        if self._empty or n == 0:
            return out
        from . import embree_native

        nat = self.native
        embree_native.blocked_many(nat.occluded1, nat.scene, np.ascontiguousarray(origins_mm, np.float64),
                                   np.ascontiguousarray(directions, np.float64),
                                   np.ascontiguousarray(lengths_mm, np.float64), out)
        return out

    def blocked_embreex(self, origins_mm: np.ndarray, directions: np.ndarray, lengths_mm: np.ndarray) -> np.ndarray:
        """:meth:`blocked` through embreex's own loop (holds the GIL): the throughput reference
        of the benchmark, and the independent check of the native path."""
        n = len(origins_mm)
        if self._empty or n == 0:
            return np.zeros(n, bool)
        hit = self._scene.run(
            np.ascontiguousarray(origins_mm, np.float32),
            np.ascontiguousarray(directions, np.float32),
            dists=np.ascontiguousarray(np.maximum(lengths_mm, 0), np.float32),
            query="OCCLUDED",
        )
        return np.asarray(hit) >= 0

    def first_hit_mm(self, origins_mm: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance along each unit direction to the first triangle hit (inf where none)."""
        n = len(origins_mm)
        if self._empty or n == 0:
            return np.full(n, np.inf)
        out = self._scene.run(np.ascontiguousarray(origins_mm, np.float32),
                              np.ascontiguousarray(directions, np.float32), output=1)
        return np.where(out["geomID"] >= 0, out["tfar"].astype(np.float64), np.inf)

    def first_hit_face(self, origins_mm: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each unit direction to the first triangle hit (inf where none) and
        that triangle's index in ``faces`` (-1 where none)."""
        n = len(origins_mm)
        if self._empty or n == 0:
            return np.full(n, np.inf), np.full(n, -1, np.int64)
        out = self._scene.run(np.ascontiguousarray(origins_mm, np.float32),
                              np.ascontiguousarray(directions, np.float32), output=1)
        hit = out["geomID"] >= 0
        return (np.where(hit, out["tfar"].astype(np.float64), np.inf),
                np.where(hit, out["primID"].astype(np.int64), -1))
