"""Sewing patterns: GarmentCode JSON in/out, the template library, and meshing into a `GarmentMesh`."""

from torch_diffavatar.pattern.garment_mesh import BoundaryLoop, GarmentMesh
from torch_diffavatar.pattern.garmentcode import (
    load_pattern,
    pattern_from_dict,
    pattern_to_dict,
    save_pattern,
)
from torch_diffavatar.pattern.library import list_templates, load_template, resolve_pattern
from torch_diffavatar.pattern.measurements import GarmentMeasurements, measure_pattern, pattern_openings
from torch_diffavatar.pattern.mesher import MeshReport, mesh_pattern, mesh_report
from torch_diffavatar.pattern.spec import Edge, EdgeRef, Panel, Pattern, Stitch

__all__ = [
    "BoundaryLoop",
    "Edge",
    "EdgeRef",
    "GarmentMeasurements",
    "GarmentMesh",
    "MeshReport",
    "Panel",
    "Pattern",
    "Stitch",
    "list_templates",
    "load_pattern",
    "load_template",
    "measure_pattern",
    "mesh_pattern",
    "mesh_report",
    "pattern_from_dict",
    "pattern_openings",
    "pattern_to_dict",
    "resolve_pattern",
    "save_pattern",
]
