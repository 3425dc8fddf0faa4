"""What a new user meets first (issue 18): readable pictures (ramp over the terrain's range with a legend,
water where the source marks it, no banding, an auto path that ends on the relief, aiming by lon/lat),
``info`` that answers where and how high, progress lines in logs, and caches outside the input's folder."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from terralod import Heightfield, build_store
from terralod.render import RenderSettings


def _utm33() -> str:
    from pyproj import CRS

    return CRS.from_epsg(32633).to_wkt()


def _store(tmp_path: Path, z: np.ndarray, name: str = "t", valid=None) -> Path:
    hf = Heightfield.from_array(z.astype(np.float32), 30.0, origin_m=(500000.0, 6400000.0), valid=valid,
                                crs=_utm33())  # fmt: skip
    out = tmp_path / f"{name}.terra"
    build_store(hf, out, tile_size=17, method="chunked", workers=2)
    return out


def _coast(n: int = 97, floor_m: float = 0.0, border: bool = True) -> np.ndarray:
    """Land rising to the east; the west third flat at ``floor_m`` (touching the west border or, with
    ``border=False``, a basin enclosed by land)."""
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 5.0 + 4.0 * c + 20.0 * np.sin(r / 7.0) ** 2
    flat = c < n // 3
    if not border:
        flat = (np.abs(r - n / 2) < n / 5) & (np.abs(c - n / 2) < n / 5)
        z = 300.0 + 0.0 * z + 10.0 * np.sin(r / 5.0) ** 2
    z[flat] = floor_m
    return z


@pytest.mark.parametrize(
    ("floor_m", "border", "sea"), [(0.0, True, True), (150.0, True, False), (0.0, False, False)]
)
def test_water_only_where_the_source_marks_a_sea(
    tmp_path: Path, floor_m: float, border: bool, sea: bool
) -> None:
    from terralod.render.offscreen import has_sea, terrain_colours
    from terralod.terrain import open_terrain

    z = _coast(floor_m=floor_m, border=border)
    with open_terrain(_store(tmp_path, z)) as t:
        assert has_sea(t) is sea
        st = terrain_colours(t, RenderSettings())
        assert (st.water_m is not None) is sea
        lo, hi = st.height_range_m
        assert lo <= hi and hi >= float(z.max()) * 0.9
        # --water-level: everything at or below it is water, whatever the terrain
        st2 = terrain_colours(t, RenderSettings(), water_level_m=42.0)
        assert st2.water_m[1] == 42.0 and st2.height_range_m[0] >= 42.0


def test_sea_is_drawn_blue_and_the_legend_reads_metres(tmp_path: Path) -> None:
    from terralod.render.offscreen import FrameRenderer, aim_pose, legend_image, terrain_colours
    from terralod.terrain import open_terrain

    with open_terrain(_store(tmp_path, _coast())) as t:
        st = terrain_colours(t, RenderSettings(fog=False, legend=True))
        w, s_, e, n = t.bounds_m
        fr = FrameRenderer(t, 160, 120, settings=st)
        tgt = (w + 0.15 * (e - w), 0.5 * (s_ + n), 0.0)
        from terralod.render.offscreen import CameraPose

        img = fr.frame(CameraPose((tgt[0], tgt[1] - 1.0, 800.0), tgt))
        fr.close()
        centre = img[55:65, 75:85].reshape(-1, 3).astype(int)
        water = np.array(st.water_colour) * 255
        assert np.abs(centre - water).max() <= 3  # the flat 0 m west is water, not lowland green
        leg = legend_image(st, 120)
        assert leg.shape[2] == 4 and (leg[:, :, 3] > 0).any()
        # the legend is in the lower-right corner of the frame only
        fr = FrameRenderer(t, 320, 240, settings=RenderSettings(legend=False))
        a = fr.frame(aim_pose(t))
        fr.settings.legend = True
        b = fr.frame(aim_pose(t))
        fr.close()
        diff = np.abs(a.astype(int) - b.astype(int)).sum(axis=2) > 0
        ys, xs = np.nonzero(diff)
        assert ys.min() > 240 // 3 and xs.min() > 320 // 2


def test_no_banding_on_flat_fogged_ground(tmp_path: Path) -> None:
    """A flat plain seen at a low angle: the fog's smooth gradient quantised to 8 bits made rings (the
    same value over wide curved bands, rarely changing from one pixel to the next: 1.2 % of horizontal
    neighbours differ without the dither); the +-1/2-step dither breaks every band edge up (33 %)."""
    from terralod.render.offscreen import FrameRenderer, aim_pose
    from terralod.terrain import open_terrain

    hf = Heightfield.from_array(np.zeros((129, 129), np.float32), 180.0, origin_m=(500000.0, 6400000.0),
                                crs=_utm33())  # fmt: skip
    build_store(hf, tmp_path / "flat.terra", tile_size=17, method="chunked")
    with open_terrain(tmp_path / "flat.terra") as t:
        fr = FrameRenderer(t, 200, 150, settings=RenderSettings())
        img = fr.frame(aim_pose(t, None, (200.0, 10.0, 8000.0)))
        fr.close()
    g = img[:, :, 1].astype(int)
    rows = np.flatnonzero(g[:, 100] < 190)  # below the horizon
    assert rows.size > 50
    g = g[rows[0] + 5 :]
    assert float((g[:, 1:] != g[:, :-1]).mean()) > 0.15


def test_auto_path_ends_over_the_relief(tmp_path: Path) -> None:
    from terralod.render.offscreen import auto_path, relief_focus
    from terralod.terrain import open_terrain

    n = 129
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 10.0 + 600.0 * np.exp(-((r - 30) ** 2 + (c - 100) ** 2) / 300.0) * (1 + 0.3 * np.sin(r) * np.cos(c))
    with open_terrain(_store(tmp_path, z)) as t:
        w, s_, e, nn = t.bounds_m
        mx, my = w + 100 * 30.0, nn - 30 * 30.0  # the mountain (col 100, row 30)
        focus, radius = relief_focus(t)
        assert math.hypot(focus[0] - mx, focus[1] - my) < 0.2 * (e - w)
        path = auto_path(t, 12)
        end = path[-1]
        assert math.hypot(end.target[0] - mx, end.target[1] - my) < 0.2 * (e - w)
        assert end.eye[2] > float(z.max())  # above the relief, not low over the plain
        first = path[0]
        assert math.hypot(first.target[0] - 0.5 * (w + e), first.target[1] - 0.5 * (s_ + nn)) < 0.2 * (e - w)


def test_aim_by_lon_lat_and_from(tmp_path: Path) -> None:
    from pyproj import Transformer

    from terralod.render.offscreen import aim_pose
    from terralod.terrain import open_terrain

    with open_terrain(_store(tmp_path, _coast())) as t:
        w, s_, e, n = t.bounds_m
        x, y = 0.5 * (w + e), 0.5 * (s_ + n)
        lon, lat = Transformer.from_crs(t.crs, "EPSG:4326", always_xy=True).transform(x, y)
        pose = aim_pose(t, (lon, lat), (90.0, 30.0, 1000.0))
        assert abs(pose.target[0] - x) < 0.01 and abs(pose.target[1] - y) < 0.01
        d = np.asarray(pose.eye) - np.asarray(pose.target)
        assert abs(np.linalg.norm(d) - 1000.0) < 1e-6
        assert d[0] > 800 and abs(d[1]) < 1e-6 and abs(math.degrees(math.asin(d[2] / 1000.0)) - 30.0) < 1e-9
        res = CliRunner().invoke(
            _cli(), ["render", str(t.path), "-o", str(tmp_path / "a.png"), "--size", "64x48",
                     "--look-at", f"{lon},{lat}", "--from", "90,30,1000"],
        )  # fmt: skip
        assert res.exit_code == 0, res.output
        bad = CliRunner().invoke(
            _cli(), ["render", str(t.path), "-o", str(tmp_path / "b.png"), "--from", "1,2"]
        )
        assert bad.exit_code == 2 and "--from" in bad.output


def _cli():
    from terralod.cli import cli

    return cli


def test_info_answers_where_and_how_high(tmp_path: Path) -> None:
    z = _coast()
    valid = np.ones(z.shape, bool)
    valid[:5, :5] = False
    store = _store(tmp_path, z, valid=valid)
    dem = tmp_path / "dem.tif"
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(dem, "w", driver="GTiff", width=97, height=97, count=1, dtype="float32", crs="EPSG:32633",
                       transform=from_origin(500000.0, 6400000.0, 30.0, 30.0), nodata=-9999.0) as ds:  # fmt: skip
        ds.write(np.where(valid, z, -9999.0).astype(np.float32), 1)
    for path in (dem, store):
        res = CliRunner().invoke(_cli(), ["info", str(path), "--json"])
        assert res.exit_code == 0, res.output
        d = json.loads(res.output)
        w, s_, e, n = d["bounds_m"]
        assert abs(w - 500000.0) < 1e-6 and abs(n - 6400000.0) < 1e-6 and abs(e - w - 97 * 30.0) < 1e-6
        lw, ls, le, ln = d["bounds_lonlat"]
        assert 14.9 < lw < le < 15.1 and 57.6 < ls < ln < 57.8  # UTM 33N at 500 km east: 15 E
        lo, hi = d["elevation_range_m"]
        assert lo <= 0.0 + 1e-3 and abs(hi - float(z[valid].max())) < 0.05
        text = CliRunner().invoke(_cli(), ["info", str(path)], terminal_width=80)
        assert text.exit_code == 0 and "lon/lat" in text.output and " km" in text.output
        for line in text.output.splitlines():
            if not line.lstrip().startswith("note"):
                assert len(line) <= 80 and "…" not in line, line


def test_plain_progress_lines(capsys: pytest.CaptureFixture[str]) -> None:
    import io

    from terralod.cli._console import PlainProgress

    buf = io.StringIO()
    with PlainProgress("building", every_s=0.0, stream=buf) as p:
        k = p.add_task("x.terra", total=None)
        for i in range(5):
            p.update(k, completed=i + 1, total=5)
    lines = buf.getvalue().splitlines()
    assert lines[0] == "building x.terra ..."
    assert lines[-1].startswith("building x.terra: 5/5 (100 %)")
    assert len(lines) == 6


def test_view_cache_goes_to_the_user_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from terralod.cli._inputs import cache_store_path

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    src = tmp_path / "ro" / "dem.tif"
    p = cache_store_path(src, "abc123")
    assert p.parent.is_relative_to(tmp_path / "cache" / "terralod") and p.suffix == ".terra"
    assert cache_store_path(src, "abc123") == p and cache_store_path(src, "other") != p
