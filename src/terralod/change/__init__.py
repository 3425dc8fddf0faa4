"""Terrain change between epochs: the DEM of difference on one grid (:mod:`.difference`), co-registration
on stable ground (:mod:`.coregister`), volumes with their uncertainty (:mod:`.volumes`; the error that
holds where the change is, σ by slope and curvature with several correlation ranges: :mod:`.uncertainty`) and the HTML
report for non-experts (:mod:`.report`). :func:`compare` runs the whole chain on two heightfields.

Nothing heavy is imported here (xdem, matplotlib and the renderer load on use).
"""

from __future__ import annotations
