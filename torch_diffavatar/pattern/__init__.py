"""Sewing patterns: GarmentCode JSON in/out, the template library, and meshing into a `GarmentMesh`."""

from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh

__all__ = ["BoundaryLoop", "GarmentMesh"]
