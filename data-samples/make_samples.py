"""Regenerate the small sample files in data-samples/ (run: python data-samples/make_samples.py).

- ``mouse.vtk``: a closed ellipsoidal "mouse" body (60 x 24 x 20 mm) whose triangles are
  grouped into 96 flux elements by the integer cell array ``element`` (12 around x 8 along).
- ``patch.ply``: a flat 10 x 10 mm square of 8 triangles (each triangle an element).
"""

from pathlib import Path

import numpy as np
import pyvista as pv

HERE = Path(__file__).resolve().parent


def mouse() -> pv.PolyData:
    body = pv.Sphere(radius=1.0, theta_resolution=36, phi_resolution=18, center=(0, 0, 0))
    body.points = np.asarray(body.points) * np.array([30.0, 12.0, 10.0]) + np.array([0, 0, 10.0])
    c = np.asarray(body.cell_centers().points) - np.array([0, 0, 10.0])
    around = ((np.arctan2(c[:, 2], c[:, 1]) + np.pi) / (2 * np.pi) * 12).astype(int) % 12
    along = np.clip(((c[:, 0] + 30) / 60 * 8).astype(int), 0, 7)
    body.cell_data["element"] = (along * 12 + around).astype(np.int32)
    return body


def patch() -> pv.PolyData:
    return pv.Plane(center=(0, 0, 0), direction=(0, 0, 1), i_size=10, j_size=10, i_resolution=2, j_resolution=2).triangulate()


if __name__ == "__main__":
    mouse().save(HERE / "mouse.vtk", binary=True)
    patch().save(HERE / "patch.ply", binary=True)
    print("wrote", HERE / "mouse.vtk", HERE / "patch.ply")
