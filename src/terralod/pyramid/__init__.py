"""Tile builders: mesh every tile of the pyramid, measure its error, write the store."""
