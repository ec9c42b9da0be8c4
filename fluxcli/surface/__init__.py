"""Surfaces: phantom generators and mesh files, grouped into flux elements."""
