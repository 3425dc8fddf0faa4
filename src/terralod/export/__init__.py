"""Web exports of any terrain: OGC 3D Tiles 1.1 (:mod:`.tiles3d`) and Cesium quantized-mesh 1.0
(:mod:`.quantized_mesh`), with the geodesy of the export boundary in :mod:`.geodesy` (pyproj)."""

from terralod.export.quantized_mesh import QuantizedMesh, export_quantized_mesh
from terralod.export.tiles3d import ExportReport, Tiles3D, export_3dtiles

__all__ = ["ExportReport", "QuantizedMesh", "Tiles3D", "export_3dtiles", "export_quantized_mesh"]
