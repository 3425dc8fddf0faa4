"""GPU rendering of selected, stitched tiles (moderngl): offscreen frames and, later, the window viewer.

Core objects never import this package; it consumes meshes as ``(code, vertices, triangles, normals)``.
"""

from terralod.render.renderer import RenderSettings, TerrainRenderer, create_offscreen_context

__all__ = ["RenderSettings", "TerrainRenderer", "create_offscreen_context"]
