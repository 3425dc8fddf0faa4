"""Readers: rasters (rasterio), PNG heightmaps and encoded tiles (Pillow), arrays, point clouds."""
