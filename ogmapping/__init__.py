"""OG-Mapping: online dense mapping with octree-managed structured 3D Gaussians."""

__version__ = "0.1.0"
