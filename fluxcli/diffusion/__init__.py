"""Diffusion forward model: tetrahedral meshing and linear FEM (as NIRFAST).

Functions take arrays in mm and powers in photons/s.
"""

from .fem import DiffusionModel, ball_quadrature, nirfast_A
from .mesh import boundary_faces, check_closed, tetrahedralize
from .transfer_to_surface import exitance_to_elements

__all__ = [
    "DiffusionModel",
    "ball_quadrature",
    "boundary_faces",
    "check_closed",
    "exitance_to_elements",
    "nirfast_A",
    "tetrahedralize",
]
