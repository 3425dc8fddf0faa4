// terralod's change site: how the ground changed between dates, for people who are not terrain experts.
// CesiumJS with its default options, no account, no internet. What it reads is described in terralod/site.
// window.terralodSite is the page's contract (the tests use it): ready, epochs, pairs, setEpoch, setSwipe,
// changeAt, volume.
"use strict";
(function () {
  const S = (window.terralodSite = { errors: [] });
  let readyResolve, readyReject;
  S.ready = new Promise((res, rej) => { readyResolve = res; readyReject = rej; });
  window.addEventListener("error", (e) => S.errors.push(String(e.message)));
  const $ = (id) => document.getElementById(id);
  const status = (t) => { $("status").textContent = t; };

  // -- numbers in words -------------------------------------------------------------------------------
  const fmtVol = (v) => {
    const a = Math.abs(v);
    if (a >= 1e9) return `${(v / 1e9).toFixed(2)} billion m³`;
    if (a >= 1e6) return `${(v / 1e6).toFixed(1)} million m³`;
    return `${Math.round(v).toLocaleString("en")} m³`;
  };
  const fmtPm = (v, u) => {
    const a = Math.max(Math.abs(v), Math.abs(u));
    if (a >= 1e6) return `${(v / 1e6).toFixed(2)} ± ${(u / 1e6).toFixed(2)} million m³`;
    return `${Math.round(v).toLocaleString("en")} ± ${Math.round(u).toLocaleString("en")} m³`;
  };
  const pools = (v, pool) => {
    const n = Math.abs(v) / pool;
    return n >= 10 ? Math.round(n).toLocaleString("en") : n.toFixed(1);
  };

  // -- data -------------------------------------------------------------------------------------------
  let site = null;
  const pairCache = new Map();
  const pairIndex = (a, b) => site.pairs.findIndex((p) => p.from === a && p.to === b);
  // a pair's description (pairs/K.json); its rasters come tile by tile (below), when an answer or the view
  // needs them
  async function loadPair(a, b) {
    const k = pairIndex(a, b);
    if (k < 0) throw new Error(`this site carries no difference from ${a} to ${b}`);
    if (!pairCache.has(k)) pairCache.set(k, fetch(site.pairs[k].url).then((r) => r.json()));
    return pairCache.get(k);
  }

  // -- rasters: a pair's difference and BEFORE heights as tile pyramids (terralod.site.tiles) ----------------
  // Level 0 is the grid (each cell's own value): changeAt and volume read only it; coarser levels (means of
  // 2^k-cell blocks) are for the drape. Tiles are int32 steps (site.json's rasters: step_m, nodata), each row
  // delta-coded, the int32s' bytes in four planes, gzip'd: inflated here, so any host serves them as they are.
  const TILE_CACHE_MAX = 96;  // decoded tiles kept (least recently used go first)
  const tileCache = new Map();  // tile URL -> Promise of its samples (Float64Array, NaN = no data)
  function levelTiles(R, level) {
    const [h, w] = R.levels[level].shape, n = R.tile_px;
    return { h, w, rows: Math.ceil(h / n), cols: Math.ceil(w / n) };
  }
  function hasTile(R, level, tr, tc) {
    const t = levelTiles(R, level);
    return tr >= 0 && tc >= 0 && tr < t.rows && tc < t.cols && R.levels[level].tiles[tr * t.cols + tc] === "1";
  }
  function decodeTile(buf, rows, cols) {
    const { step_m: step, nodata } = site.rasters, n = rows * cols, b = new Uint8Array(buf);
    if (b.length !== 4 * n) throw new Error(`a tile of ${b.length} bytes is not ${rows} x ${cols} int32s`);
    const out = new Float64Array(n);
    for (let r = 0; r < rows; r++) {
      let acc = 0;
      for (let i = r * cols, end = i + cols; i < end; i++) {
        acc = (acc + (b[i] | (b[n + i] << 8) | (b[2 * n + i] << 16) | (b[3 * n + i] << 24))) | 0;
        out[i] = acc === nodata ? NaN : acc * step;
      }
    }
    return out;
  }
  // tile (tr, tc) of a level: {data, rows, cols, r0, c0} (r0, c0: its first sample in the level), null where
  // the pyramid has none (no data there)
  function getTile(R, level, tr, tc) {
    if (!hasTile(R, level, tr, tc)) return Promise.resolve(null);
    const url = `${R.url}/${level}/${tr}_${tc}.i32.gz`;
    let got = tileCache.get(url);
    if (got) { tileCache.delete(url); tileCache.set(url, got); return got; }
    got = (async () => {
      const res = await fetch(url);
      if (!res.ok) throw new Error(`${url}: HTTP ${res.status}`);
      const buf = await new Response(res.body.pipeThrough(new DecompressionStream("gzip"))).arrayBuffer();
      const n = R.tile_px, { h, w } = levelTiles(R, level);
      const rows = Math.min(n, h - tr * n), cols = Math.min(n, w - tc * n);
      return { data: decodeTile(buf, rows, cols), rows, cols, r0: tr * n, c0: tc * n };
    })();
    got.catch(() => tileCache.delete(url));
    tileCache.set(url, got);
    while (tileCache.size > TILE_CACHE_MAX) tileCache.delete(tileCache.keys().next().value);
    return got;
  }
  // one cell of level 0 (the cell's own value), NaN outside the grid or where there is no data
  async function cellValue(R, row, col) {
    const n = R.tile_px, t = await getTile(R, 0, Math.floor(row / n), Math.floor(col / n));
    return t ? t.data[(row - t.r0) * t.cols + (col - t.c0)] : NaN;
  }
  S.tileCacheSize = () => tileCache.size;
  // lon/lat (degrees) -> fractional grid (col, row): the lattice of grid-CRS coordinates, then the affine
  function toGrid(P, lon, lat) {
    const L = P.lattice, n = L.nodes;
    let fi = (lon - L.lon0_deg) / L.dlon_deg, fj = (lat - L.lat0_deg) / L.dlat_deg;
    fi = Math.min(Math.max(fi, 0), n - 1.000001); fj = Math.min(Math.max(fj, 0), n - 1.000001);
    const i = Math.floor(fi), j = Math.floor(fj), ti = fi - i, tj = fj - j;
    const at = (arr) => {
      const a = arr[j * n + i], b = arr[j * n + i + 1], c = arr[(j + 1) * n + i], d = arr[(j + 1) * n + i + 1];
      return (a * (1 - ti) + b * ti) * (1 - tj) + (c * (1 - ti) + d * ti) * tj;
    };
    const x = at(L.x_m), y = at(L.y_m);
    const [a, b, c, d, e, f] = P.grid.transform;
    const det = a * e - b * d;
    return [(e * (x - c) - b * (y - f)) / det, (-d * (x - c) + a * (y - f)) / det];
  }
  // the ± at the confidence level of a volume over area_m2 (Rolstad et al. 2009 + nugget, as the report)
  function volumeUncertainty(P, area) {
    const m = P.error_model, a = P.grid.cell_area_m2;
    if (area <= 0) return 0;
    const corr = m.range_m > 0 ? Math.min(1, Math.PI * m.range_m ** 2 / (5 * area)) : 0;
    const v = m.nugget_m2 * Math.min(1, a / area) + m.sill_m2 * corr;
    return m.t * area * Math.sqrt(Math.max(v, 0));
  }
  const num = (v) => (Number.isFinite(v) ? v : null);
  S.changeAt = async (lon, lat, from, to) => {
    const P = await loadPair(from, to);
    const [h, w] = P.grid.shape;
    const [col, row] = toGrid(P, lon, lat);
    const c = Math.floor(col), r = Math.floor(row);
    const inside = c >= 0 && r >= 0 && c < w && r < h;
    const [d, b] = inside ? await Promise.all([cellValue(P.rasters.dod, r, c), cellValue(P.rasters.before, r, c)]) : [NaN, NaN];
    return { before_m: num(b), after_m: num(b + d), change_m: num(d), lod_m: P.error_model.lod_m,
      uncertainty_m: volumeUncertainty(P, P.grid.cell_area_m2) / P.grid.cell_area_m2, row: r, col: c };
  };
  // the volume inside a polygon: the level-0 tiles it covers, streamed (a few at a time), each cell whose centre
  // lies inside counted once (the rule of terralod change --zones)
  S.volume = async (ring, from, to) => {
    const P = await loadPair(from, to);
    const R = P.rasters.dod, [h, w] = P.grid.shape, n = R.tile_px;
    const pts = ring.map(([lo, la]) => toGrid(P, lo, la));
    if (pts.length > 1 && pts[0][0] === pts[pts.length - 1][0] && pts[0][1] === pts[pts.length - 1][1]) pts.pop();
    if (pts.length < 3) throw new Error("a polygon needs at least three corners");
    const r0 = Math.max(0, Math.floor(Math.min(...pts.map((p) => p[1])))), r1 = Math.min(h - 1, Math.ceil(Math.max(...pts.map((p) => p[1]))));
    const spans = new Map();  // row -> [first col, last col, ...] of the cells whose centre lies inside
    let c0 = w, c1 = -1;
    for (let r = r0; r <= r1; r++) {
      const yc = r + 0.5, xs = [];
      for (let k = 0, m = pts.length - 1; k < pts.length; m = k++) {  // crossings of the row's centre line
        const [xa, ya] = pts[k], [xb, yb] = pts[m];
        if ((ya > yc) !== (yb > yc)) xs.push(xa + (yc - ya) * (xb - xa) / (yb - ya));
      }
      xs.sort((p, q) => p - q);
      const row = [];
      for (let k = 0; k + 1 < xs.length; k += 2) {
        const a = Math.max(0, Math.ceil(xs[k] - 0.5)), b = Math.min(w - 1, Math.floor(xs[k + 1] - 0.5));
        if (a <= b) { row.push(a, b); c0 = Math.min(c0, a); c1 = Math.max(c1, b); }
      }
      if (row.length) spans.set(r, row);
    }
    const jobs = [];
    for (let tr = Math.floor(r0 / n); tr <= Math.floor(r1 / n); tr++)
      for (let tc = Math.floor(c0 / n); c1 >= 0 && tc <= Math.floor(c1 / n); tc++) jobs.push([tr, tc]);
    let gain = 0, loss = 0, net = 0, cells = 0;
    const sumTile = (t) => {
      for (let r = t.r0; r < t.r0 + t.rows; r++) {
        const row = spans.get(r);
        if (!row) continue;
        for (let k = 0; k < row.length; k += 2) {
          const a = Math.max(row[k], t.c0), b = Math.min(row[k + 1], t.c0 + t.cols - 1);
          for (let c = a, i = (r - t.r0) * t.cols + (a - t.c0); c <= b; c++, i++) {
            const v = t.data[i];
            if (!Number.isFinite(v)) continue;
            cells++; net += v;
            if (v > 0) gain += v; else loss -= v;
          }
        }
      }
    };
    const worker = async () => { for (let j = jobs.shift(); j; j = jobs.shift()) { const t = await getTile(R, 0, j[0], j[1]); if (t) sumTile(t); } };
    await Promise.all([worker(), worker(), worker(), worker()]);
    const a = P.grid.cell_area_m2;
    return { gain_m3: gain * a, loss_m3: loss * a, net_m3: net * a, net_uncertainty_m3: volumeUncertainty(P, cells * a),
      cells, area_m2: cells * a };
  };

  // -- the globe --------------------------------------------------------------------------------------
  // The page's state: the manifest, the viewer, one tileset per epoch and what is shown (mode, dates).
  const page = { view: { mode: "one", current: null, swipeA: null, swipeB: null } };

  async function readManifest() {
    site = await (await fetch("site.json")).json();
    S.site = site;
    S.epochs = site.epochs.map((e) => e.name);
    S.pairs = site.pairs.map((p) => [p.from, p.to]);
    document.title = site.title;
    $("title").textContent = site.title;
    page.labelOf = (name) => (site.epochs.find((e) => e.name === name) || { label: name }).label;
    page.first = S.epochs[0];
    page.last = S.epochs[S.epochs.length - 1];
    const { labelOf, first, last } = page;
    $("dates").textContent = S.epochs.length > 1 ? `${S.epochs.length} surveys, ${labelOf(first)} to ${labelOf(last)}` : labelOf(first);
    Object.assign(page.view, { current: first, swipeA: first, swipeB: last });
  }

  function makeViewer() {
    const viewer = new Cesium.Viewer("globe", {
      baseLayer: false, baseLayerPicker: false, geocoder: false, timeline: false, animation: false, homeButton: false,
      sceneModePicker: false, navigationHelpButton: false, fullscreenButton: false, infoBox: false,
      selectionIndicator: false, skyBox: false, skyAtmosphere: false,
      contextOptions: { webgl: { preserveDrawingBuffer: true } },
    });
    S.viewer = page.viewer = viewer;
    const scene = (page.scene = viewer.scene);
    scene.globe.show = false;  // 3D Tiles carry the terrain; no empty globe around (or through) it
    if (scene.sun) scene.sun.show = false;
    if (scene.moon) scene.moon.show = false;
    scene.backgroundColor = Cesium.Color.fromCssColorString("#dfe6ec");
    scene.fog.enabled = false;

    const [w, s, e, n] = site.bounds_deg;
    const [zlo, zhi] = site.elevation_range_m;
    page.bounds = { w, s, e, n, zlo, zhi };
    const centre = (page.centre = Cesium.Cartesian3.fromDegrees((w + e) / 2, (s + n) / 2, (zlo + zhi) / 2));
    const enu = Cesium.Transforms.eastNorthUpToFixedFrame(centre);
    const toLight = Cesium.Matrix4.multiplyByPointAsVector(enu, new Cesium.Cartesian3(-0.5, 0.5, 0.7071), new Cesium.Cartesian3());
    scene.light = new Cesium.DirectionalLight({ direction: Cesium.Cartesian3.normalize(Cesium.Cartesian3.negate(toLight, new Cesium.Cartesian3()), new Cesium.Cartesian3()), intensity: 2.0 });
  }

  // each tileset's shader: shaded by height, the drape of a pair on top when u_drape is set
  const blank = "data:image/png;base64,iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mNkYPhfDwAChwGA60e6kgAAAABJRU5ErkJggg==";
  function makeShader() {
    const centre = page.centre, { zlo, zhi } = page.bounds;
    return new Cesium.CustomShader({
      lightingModel: Cesium.LightingModel.PBR,
      uniforms: {
        u_overlay: { type: Cesium.UniformType.SAMPLER_2D, value: new Cesium.TextureUniform({ url: blank }) },
        u_drape: { type: Cesium.UniformType.FLOAT, value: 0.0 },
        u_centre: { type: Cesium.UniformType.VEC3, value: new Cesium.Cartesian3() },
        u_east: { type: Cesium.UniformType.VEC3, value: new Cesium.Cartesian3(1, 0, 0) },
        u_north: { type: Cesium.UniformType.VEC3, value: new Cesium.Cartesian3(0, 1, 0) },
        u_u: { type: Cesium.UniformType.VEC3, value: new Cesium.Cartesian3() },
        u_v: { type: Cesium.UniformType.VEC3, value: new Cesium.Cartesian3() },
        u_win: { type: Cesium.UniformType.VEC4, value: new Cesium.Cartesian4(0, 0, 1, 1) },
        u_zc: { type: Cesium.UniformType.VEC3, value: centre },
        u_up: { type: Cesium.UniformType.VEC3, value: Cesium.Cartesian3.normalize(centre, new Cesium.Cartesian3()) },
        u_range: { type: Cesium.UniformType.VEC2, value: new Cesium.Cartesian2(zlo, zhi) },
      },
      fragmentShaderText: `
        void fragmentMain(FragmentInput fsInput, inout czm_modelMaterial material) {
          vec3 p = fsInput.attributes.positionWC;
          float h = (u_range.x + u_range.y) * 0.5 + dot(p - u_zc, u_up);
          float t = clamp((h - u_range.x) / max(u_range.y - u_range.x, 1.0), 0.0, 1.0);
          vec3 base = mix(vec3(0.80, 0.78, 0.70), vec3(0.95, 0.94, 0.92), t);
          material.diffuse = base;
          if (u_drape > 0.5) {
            vec3 d = p - u_centre;
            float e = dot(d, u_east), n = dot(d, u_north);
            vec2 g = vec2(u_u.x + u_u.y * e + u_u.z * n, u_v.x + u_v.y * e + u_v.z * n);  // col / w, row / h
            vec2 uv = (g - u_win.xy) / u_win.zw;  // in the drawn window: its first row first
            if (g.x >= 0.0 && g.x <= 1.0 && g.y >= 0.0 && g.y <= 1.0 && uv.x >= 0.0 && uv.x <= 1.0 && uv.y >= 0.0 && uv.y <= 1.0) {
              vec4 c = texture(u_overlay, uv);
              material.diffuse = mix(base, c.rgb, c.a);
            }
          }
        }`,
    });
  }

  async function loadTilesets() {
    const tilesets = [];
    for (const ep of site.epochs) {
      const ts = await Cesium.Cesium3DTileset.fromUrl(ep.tileset, { preloadWhenHidden: true });
      ts.show = false;
      ts.customShader = makeShader();
      ts.tileFailed.addEventListener((err) => S.errors.push(`tile ${err.url}: ${err.message}`));
      page.scene.primitives.add(ts);
      tilesets.push(ts);
    }
    S.tilesets = page.tilesets = tilesets;
  }

  const epochIndex = (name) => {
    const i = S.epochs.indexOf(name);
    if (i < 0) throw new Error(`no epoch named ${name}`);
    return i;
  };

  // the drape: the part of the difference in view, coloured here with the legend's table, at the pyramid's
  // level whose samples are about the screen's pixels (at most one sample per device pixel across the view)
  function viewWindow(P) {
    const [h, w] = P.grid.shape, rect = page.viewer.camera.computeViewRectangle();
    if (!rect) return [0, h, 0, w];
    const deg = Cesium.Math.toDegrees, corners = [];
    for (const fx of [0, 0.5, 1]) for (const fy of [0, 0.5, 1])
      corners.push(toGrid(P, deg(rect.west + fx * (rect.east - rect.west)), deg(rect.south + fy * (rect.north - rect.south))));
    const cs = corners.map((p) => p[0]), rs = corners.map((p) => p[1]);
    const padC = 0.1 * (Math.max(...cs) - Math.min(...cs)), padR = 0.1 * (Math.max(...rs) - Math.min(...rs));
    const r0 = Math.max(0, Math.floor(Math.min(...rs) - padR)), r1 = Math.min(h, Math.ceil(Math.max(...rs) + padR));
    const c0 = Math.max(0, Math.floor(Math.min(...cs) - padC)), c1 = Math.min(w, Math.ceil(Math.max(...cs) + padC));
    return r1 > r0 && c1 > c0 ? [r0, r1, c0, c1] : [0, h, 0, w];
  }
  function drapePlan(P) {
    const R = P.rasters.dod, n = R.tile_px, [r0, r1, c0, c1] = viewWindow(P);
    const px = Math.max(page.scene.drawingBufferWidth || page.scene.canvas.width, page.scene.drawingBufferHeight || page.scene.canvas.height, 256);
    let level = 0;
    while (level < R.levels.length - 1 && Math.max(r1 - r0, c1 - c0) / 2 ** level > px) level++;
    const f = 2 ** level, t = levelTiles(R, level);
    const tr0 = Math.floor(r0 / f / n), tr1 = Math.min(t.rows - 1, Math.floor((r1 - 1) / f / n));
    const tc0 = Math.floor(c0 / f / n), tc1 = Math.min(t.cols - 1, Math.floor((c1 - 1) / f / n));
    return { level, tr0, tr1, tc0, tc1, key: `${R.url} ${level} ${tr0} ${tr1} ${tc0} ${tc1}` };
  }
  function paintTile(P, t, rgba, cols, r0, c0) {
    const L = P.legend, lut = L.lut_rgb, nl = lut.length / 3, lod = L.lod_m;
    for (let r = 0; r < t.rows; r++) {
      for (let c = 0, i = r * t.cols, o = 4 * ((r0 + r) * cols + c0); c < t.cols; c++, i++, o += 4) {
        const v = t.data[i];
        if (!Number.isFinite(v)) continue;  // transparent: no data
        if (Math.abs(v) <= lod) { rgba.set(L.lod_rgba, o); continue; }
        const x = v < 0 ? 0.5 - 0.5 * Math.min(1, v / L.min_m) : 0.5 + 0.5 * Math.min(1, v / L.max_m);
        const k = 3 * Math.min(nl - 1, Math.floor(x * nl));
        rgba[o] = lut[k]; rgba[o + 1] = lut[k + 1]; rgba[o + 2] = lut[k + 2]; rgba[o + 3] = L.alpha;
      }
    }
  }
  // the drape's texture of a plan: its RGBA (the window's first row first) and where it lies in the grid
  async function drapeImage(P, plan) {
    const R = P.rasters.dod, n = R.tile_px, f = 2 ** plan.level, t = levelTiles(R, plan.level);
    const [h, w] = P.grid.shape;
    const rows = Math.min(t.h, (plan.tr1 + 1) * n) - plan.tr0 * n, cols = Math.min(t.w, (plan.tc1 + 1) * n) - plan.tc0 * n;
    const rgba = new Uint8Array(4 * rows * cols), jobs = [];
    for (let tr = plan.tr0; tr <= plan.tr1; tr++)
      for (let tc = plan.tc0; tc <= plan.tc1; tc++)
        jobs.push(getTile(R, plan.level, tr, tc).then((tile) => tile && paintTile(P, tile, rgba, cols, tile.r0 - plan.tr0 * n, tile.c0 - plan.tc0 * n)));
    await Promise.all(jobs);
    return { rgba, rows, cols, win: [(plan.tc0 * n * f) / w, (plan.tr0 * n * f) / h, (cols * f) / w, (rows * f) / h] };
  }
  // pair (a -> b) on tileset i (a === null: none)
  const drapeOn = new Map();  // tileset index -> {pair, key}
  async function drape(i, a, b) {
    const sh = page.tilesets[i].customShader;
    if (!$("drape").checked || a === null || pairIndex(a, b) < 0) {
      sh.setUniform("u_drape", 0.0); drapeOn.delete(i);
      if (!drapeOn.size) $("legend").hidden = true;
      return null;
    }
    const P = await loadPair(a, b);
    const plan = drapePlan(P), was = drapeOn.get(i);
    drapeOn.set(i, { pair: [a, b], key: plan.key });
    if (!was || was.key !== plan.key || was.pair[0] !== a || was.pair[1] !== b) {
      const img = await drapeImage(P, plan);
      if ((drapeOn.get(i) || {}).key !== plan.key) return P;  // the view or the pair moved on meanwhile
      sh.setUniform("u_overlay", new Cesium.TextureUniform({ typedArray: img.rgba, width: img.cols, height: img.rows, repeat: false }));
      sh.setUniform("u_win", new Cesium.Cartesian4(...img.win));
    }
    const D = P.drape;
    sh.setUniform("u_centre", Cesium.Cartesian3.fromArray(D.centre_ecef));
    sh.setUniform("u_east", Cesium.Cartesian3.fromArray(D.east));
    sh.setUniform("u_north", Cesium.Cartesian3.fromArray(D.north));
    sh.setUniform("u_u", Cesium.Cartesian3.fromArray(D.u));
    sh.setUniform("u_v", Cesium.Cartesian3.fromArray(D.v));
    sh.setUniform("u_drape", 1.0);
    showLegend(P);
    return P;
  }
  // when the camera stops, each drape is redrawn for the new view (tiles already fetched are reused)
  function wireDrapeFollowsView() {
    page.viewer.camera.moveEnd.addEventListener(() => {
      for (const [i, { pair }] of [...drapeOn]) drape(i, pair[0], pair[1]).catch((err) => S.errors.push("drape: " + err));
    });
  }
  function showLegend(P) {
    // two slopes, as the report's colour bar: 0 in the middle, each side scaled to its own extreme
    const L = P.legend, pos = (v) => (v >= 0 ? 50 + (50 * v) / L.max_m : 50 - (50 * v) / L.min_m);
    const stops = L.stops.map((st) => `${st.css} ${pos(st.value_m).toFixed(1)}%`);
    const g0 = pos(-L.lod_m).toFixed(1), g1 = pos(L.lod_m).toFixed(1);
    const grad = [...stops.slice(0, 3), `${L.lod_css} ${g0}%`, `${L.lod_css} ${g1}%`, ...stops.slice(3)];
    $("legend-bar").style.background = `linear-gradient(to right, ${grad.join(", ")})`;
    const ticks = [L.min_m, L.min_m / 2, 0, L.max_m / 2, L.max_m];
    const big = Math.max(L.max_m, -L.min_m) >= 20;
    $("legend-ticks").innerHTML = ticks.map((v) => `<span style="left:${pos(v)}%">${v === 0 ? "0" : (v > 0 ? "+" : "−") + Math.abs(v).toFixed(big ? 0 : 1)} m</span>`).join("");
    $("legend-lod").innerHTML = `<i></i> grey: within ±${L.lod_m.toFixed(1)} m, no measurable change`;
    $("legend-title").textContent = `Change in ground height, ${page.labelOf(P.from)} to ${page.labelOf(P.to)}`;
    $("legend").hidden = false;
  }

  // waiting for what is shown to be drawn
  const drawn = (list) => new Promise((resolve) => {
    const scene = page.scene, t0 = performance.now();
    const check = () => {
      if (list.every((t) => t.tilesLoaded) || performance.now() - t0 > 120000) {
        scene.requestRender();
        const once = () => { scene.postRender.removeEventListener(once); resolve(); };
        scene.postRender.addEventListener(once);
      } else setTimeout(check, 100);
    };
    setTimeout(check, 50);
  });

  // modes: one date (draped with the change since the first), or a swipe between two
  async function setEpoch(name) {
    const { tilesets, view, first, labelOf } = page;
    const i = epochIndex(name);
    view.mode = "one"; view.current = name;
    $("mode-one").classList.add("on"); $("mode-swipe").classList.remove("on");
    $("swipe").hidden = true; $("swipe-labels").hidden = true;
    tilesets.forEach((t, k) => { t.show = k === i; t.splitDirection = Cesium.SplitDirection.NONE; });
    $("epoch").value = String(i);
    $("epoch-name").textContent = labelOf(name);
    await drape(i, i > 0 ? first : null, name);
    if (i === 0) $("legend").hidden = true;
    await drawn([tilesets[i]]);
  }
  async function setSwipe(a, b, position = 0.5) {
    const { tilesets, view, scene, labelOf } = page;
    const ia = epochIndex(a), ib = epochIndex(b);
    view.mode = "swipe"; view.swipeA = a; view.swipeB = b;
    $("mode-swipe").classList.add("on"); $("mode-one").classList.remove("on");
    tilesets.forEach((t, k) => { t.show = k === ia || k === ib; t.splitDirection = Cesium.SplitDirection.NONE; });
    tilesets[ia].splitDirection = Cesium.SplitDirection.LEFT;
    tilesets[ib].splitDirection = Cesium.SplitDirection.RIGHT;
    scene.splitPosition = position;
    $("swipe").hidden = false; $("swipe-labels").hidden = false;
    placeSwipe(position);
    $("swipe-left").textContent = labelOf(a); $("swipe-right").textContent = labelOf(b);
    await drape(ia, null, a);
    await drape(ib, a, b);
    await drawn([tilesets[ia], tilesets[ib]]);
  }
  function placeSwipe(pos) {
    const W = page.scene.canvas.clientWidth;
    $("swipe").style.left = `${pos * 100}%`;
    const l = $("swipe-left"), r = $("swipe-right");
    l.style.right = `${W * (1 - pos) + 12}px`; l.style.left = "auto";
    r.style.left = `${W * pos + 12}px`;
  }
  function wireModes() {
    const { scene, view, first, last } = page;
    const slider = $("epoch");
    slider.max = String(Math.max(0, S.epochs.length - 1));
    if (S.epochs.length < 2) { $("mode-row").hidden = true; $("action-row").hidden = true; $("epoch-row").hidden = true; }
    S.setEpoch = setEpoch;
    S.setSwipe = setSwipe;
    // dragging the swipe handle
    let dragging = false;
    $("swipe-handle").addEventListener("pointerdown", (ev) => { dragging = true; ev.preventDefault(); });
    window.addEventListener("pointerup", () => { dragging = false; });
    window.addEventListener("pointermove", (ev) => {
      if (!dragging) return;
      const pos = Math.min(0.98, Math.max(0.02, ev.clientX / scene.canvas.clientWidth));
      scene.splitPosition = pos; placeSwipe(pos);
    });
    slider.addEventListener("input", () => {
      const name = S.epochs[+slider.value];
      if (view.mode === "one") setEpoch(name); else setSwipe(first === name ? S.epochs[0] : first, name, scene.splitPosition);
    });
    $("mode-one").addEventListener("click", () => setEpoch(view.current));
    $("mode-swipe").addEventListener("click", () => setSwipe(first, view.current === first ? last : view.current, 0.5));
    $("drape").addEventListener("change", () => (view.mode === "one" ? setEpoch(view.current) : setSwipe(view.swipeA, view.swipeB, scene.splitPosition)));
  }

  // the pair the answers refer to: first -> shown (one date) or left -> right (swipe)
  function activePair() {
    const { view, first, last } = page;
    if (view.mode === "swipe") return pairIndex(view.swipeA, view.swipeB) >= 0 ? [view.swipeA, view.swipeB] : [first, last];
    return view.current !== first && pairIndex(first, view.current) >= 0 ? [first, view.current] : [first, last];
  }

  // what the heights are above: "above sea level" only when the survey's datum is a geoid (site.json)
  function heightWords() {
    return (site.heights && site.heights.words) || "as surveyed";
  }

  // "how much changed here?" in a sentence
  async function describeChange(lon, lat) {
    const [a, b] = activePair();
    const r = await S.changeAt(lon, lat, a, b);
    const when = `between ${page.labelOf(a)} and ${page.labelOf(b)}`;
    if (r.change_m === null) return "No data here.";
    const u = r.uncertainty_m.toFixed(1);
    if (Math.abs(r.change_m) <= r.lod_m) return `Here the ground did not change measurably ${when} (less than ±${r.lod_m.toFixed(1)} m).`;
    const verb = r.change_m > 0 ? "rose" : "dropped";
    return `Here the ground ${verb} ${Math.abs(r.change_m).toFixed(1)} ± ${u} m ${when} (from ${r.before_m.toFixed(0)} m to ${r.after_m.toFixed(0)} m ${heightWords()}).`;
  }

  // the volume inside a drawn polygon in a sentence
  async function describeVolume(ring) {
    const [a, b] = activePair();
    const v = await S.volume(ring, a, b);
    const P = await loadPair(a, b);
    const pool = P.olympic_pool_m3;
    const net = v.net_m3 >= 0 ? `a net gain of ${fmtPm(v.net_m3, v.net_uncertainty_m3)}` : `a net loss of ${fmtPm(-v.net_m3, v.net_uncertainty_m3)}`;
    return `Inside this shape (${(v.area_m2 / 1e6).toFixed(2)} km²), between ${page.labelOf(a)} and ${page.labelOf(b)}: ${net} ` +
      `(about ${pools(v.net_m3, pool)} Olympic swimming pools); ${fmtVol(v.gain_m3)} added where the ground rose, ` +
      `${fmtVol(v.loss_m3)} removed where it dropped.`;
  }

  // clicks on the ground: a sentence on the change there, or a corner of the polygon being drawn
  const drawing = { on: false, ring: [], entity: null };
  function wireClicks() {
    const scene = page.scene;
    S.describeChange = describeChange;
    S.describeVolume = describeVolume;
    const handler = new Cesium.ScreenSpaceEventHandler(scene.canvas);
    const pick = (pos) => {
      const p = scene.pickPosition(pos);
      if (!Cesium.defined(p)) return null;
      const c = Cesium.Cartographic.fromCartesian(p);
      return [Cesium.Math.toDegrees(c.longitude), Cesium.Math.toDegrees(c.latitude)];
    };
    handler.setInputAction(async (click) => {
      const ll = pick(click.position);
      if (!ll) return;
      if (drawing.on) { drawing.ring.push(ll); updateRing(); return; }
      $("answer").textContent = await describeChange(ll[0], ll[1]);
    }, Cesium.ScreenSpaceEventType.LEFT_CLICK);
  }

  // the polygon being drawn, lifted onto the terrain
  function updateRing() {
    const { viewer, scene } = page;
    if (drawing.entity) viewer.entities.remove(drawing.entity);
    if (drawing.ring.length < 2) return;
    const flat = drawing.ring.concat([drawing.ring[0]]).flat();
    drawing.entity = viewer.entities.add({ polyline: { positions: Cesium.Cartesian3.fromDegreesArray(flat), width: 3,
      material: Cesium.Color.YELLOW, clampToGround: false, depthFailMaterial: Cesium.Color.YELLOW } });
    // lift the outline onto the terrain so it is seen
    Promise.all(drawing.ring.map(([lo, la]) => scene.sampleHeightMostDetailed([Cesium.Cartographic.fromDegrees(lo, la)])))
      .then((hs) => {
        if (!drawing.entity) return;
        const pts = drawing.ring.map(([lo, la], k) => Cesium.Cartesian3.fromDegrees(lo, la, ((hs[k][0] && hs[k][0].height) || 0) + 5));
        drawing.entity.polyline.positions = pts.concat([pts[0]]);
      }).catch(() => {});
    $("answer").textContent = `Corners: ${drawing.ring.length}. Click more, then press "Done".`;
  }

  // "Measure a volume": the first press starts a polygon, the second measures it
  function wireMeasure() {
    $("measure").addEventListener("click", async () => {
      if (!drawing.on) {
        drawing.on = true; drawing.ring = [];
        if (drawing.entity) { page.viewer.entities.remove(drawing.entity); drawing.entity = null; }
        $("measure").textContent = "Done"; $("measure").classList.add("on");
        $("answer").textContent = "Click the corners of the area on the ground, then press \"Done\".";
        return;
      }
      drawing.on = false;
      $("measure").textContent = "Measure a volume"; $("measure").classList.remove("on");
      if (drawing.ring.length < 3) { $("answer").textContent = "A shape needs at least three corners."; return; }
      $("answer").textContent = await describeVolume(drawing.ring);
    });
  }

  // "the largest change": fly there and say it
  function wireLargest() {
    $("largest").addEventListener("click", async () => {
      const [a, b] = activePair();
      const P = await loadPair(a, b);
      if (!P.largest) return;
      const { lon_deg, lat_deg } = P.largest;
      const r = await S.changeAt(lon_deg, lat_deg, a, b);
      const target = Cesium.Cartesian3.fromDegrees(lon_deg, lat_deg, r.after_m || 0);
      // far enough to see the change around it: three radii of a disc of the area that changed measurably
      // (St Helens' dome: 2.3 km, so the 2.5 km floor; a 47 km² mound: 12 km), at most 200 km
      const t = P.totals || {};
      const area = Math.max(t.area_gain_m2 || 0, t.area_loss_m2 || 0);
      const range = Math.min(200000, Math.max(2500, 3 * Math.sqrt(area / Math.PI)));
      page.viewer.camera.flyToBoundingSphere(new Cesium.BoundingSphere(target, range / 4), { offset: new Cesium.HeadingPitchRange(0, Cesium.Math.toRadians(-40), range), duration: 2 });
      $("answer").textContent = await describeChange(lon_deg, lat_deg);
    });
  }

  // a series: play through the dates, and the volume against time
  function wireSeries() {
    if (S.epochs.length <= 2) return;
    $("play").hidden = false;
    let timer = null;
    $("play").addEventListener("click", () => {
      if (timer) { clearInterval(timer); timer = null; $("play").textContent = "▶ Play"; return; }
      $("play").textContent = "❚❚ Pause";
      let i = S.epochs.indexOf(page.view.current);
      timer = setInterval(() => { i = (i + 1) % S.epochs.length; setEpoch(S.epochs[i]); }, 1500);
    });
    drawChart(page.labelOf).catch((err) => S.errors.push("chart: " + err));
  }

  // scale bar and north arrow follow the camera
  function wireScaleAndNorth() {
    const { viewer, scene } = page;
    scene.postRender.addEventListener(() => {
      $("north-needle").setAttribute("transform", `rotate(${-Cesium.Math.toDegrees(viewer.camera.heading)})`);
      const cv = scene.canvas, y = cv.clientHeight - 30;
      const p0 = viewer.camera.pickEllipsoid(new Cesium.Cartesian2(60, y)), p1 = viewer.camera.pickEllipsoid(new Cesium.Cartesian2(160, y));
      if (!p0 || !p1) return;
      const mPer100 = Cesium.Cartesian3.distance(p0, p1);
      const nice = [1, 2, 5].flatMap((k) => [1, 10, 100, 1000, 10000, 100000].map((m) => k * m)).sort((p, q) => p - q);
      const len = nice.filter((v) => v <= mPer100 * 1.5).pop() || nice[0];
      $("scale-bar").style.width = `${(100 * len) / mPer100}px`;
      $("scale-text").textContent = len >= 1000 ? `${len / 1000} km` : `${len} m`;
    });
  }

  // first view: the whole terrain, from the south-south-west, looking down 50°
  function firstView() {
    const { viewer, centre } = page, { w, s, e, n, zlo } = page.bounds;
    const diag = Cesium.Cartesian3.distance(Cesium.Cartesian3.fromDegrees(w, s, zlo), Cesium.Cartesian3.fromDegrees(e, n, zlo));
    viewer.camera.lookAt(centre, new Cesium.HeadingPitchRange(0.0, Cesium.Math.toRadians(-50), 1.1 * diag));
    viewer.camera.lookAtTransform(Cesium.Matrix4.IDENTITY);
    viewer.camera.moveLeft(0.18 * diag);  // the terrain to the right of the panel
  }

  // the plain-language summary of the main pair
  async function showSummary() {
    if (!site.pairs.length) { $("summary-box").hidden = true; return; }
    const P = await loadPair(page.first, page.last);
    $("summary").innerHTML = "";
    for (const line of P.summary) { const li = document.createElement("li"); li.textContent = line; $("summary").appendChild(li); }
  }

  async function main() {
    if (typeof Cesium === "undefined") throw new Error("CesiumJS did not load (cesium/ missing from this folder)");
    await readManifest();
    makeViewer();
    await loadTilesets();
    wireModes();
    wireClicks();
    wireMeasure();
    wireLargest();
    wireSeries();
    wireScaleAndNorth();
    firstView();
    wireDrapeFollowsView();
    await showSummary();
    const t0 = performance.now();
    await setEpoch(S.epochs.length > 1 ? page.last : page.first);
    S.firstViewMs = performance.now() - t0;
    status(`${S.epochs.length} date${S.epochs.length > 1 ? "s" : ""} · drawn with ${page.scene.context.webgl2 ? "WebGL 2" : "WebGL"}`);
  }

  async function drawChart(labelOf) {
    // net volume since the first date, each date's own pair (first -> that date) with its ±
    const pts = [{ x: 0, v: 0, u: 0 }];
    for (let i = 1; i < S.epochs.length; i++) {
      const k = pairIndex(S.epochs[0], S.epochs[i]);
      if (k < 0) return;
      const meta = await (await fetch(site.pairs[k].url)).json();
      pts.push({ x: i, v: meta.totals.net_m3, u: meta.totals.net_uncertainty_m3 });
    }
    const W = 320, H = 150, pad = 34;
    const lo = Math.min(0, ...pts.map((p) => p.v - p.u)), hi = Math.max(0, ...pts.map((p) => p.v + p.u));
    const X = (i) => pad + (i / (pts.length - 1)) * (W - pad - 8), Y = (val) => H - 20 - ((val - lo) / (hi - lo || 1)) * (H - 30);
    const line = pts.map((p, i) => `${i ? "L" : "M"}${X(p.x).toFixed(1)},${Y(p.v).toFixed(1)}`).join("");
    const band = pts.map((p) => `${X(p.x).toFixed(1)},${Y(p.v + p.u).toFixed(1)}`).concat(pts.slice().reverse().map((p) => `${X(p.x).toFixed(1)},${Y(p.v - p.u).toFixed(1)}`)).join(" ");
    const unit = Math.max(Math.abs(lo), Math.abs(hi)) >= 1e6 ? 1e6 : 1;
    $("chart").innerHTML = `<div><b>Volume since ${labelOf(S.epochs[0])}</b> (${unit === 1e6 ? "million m³" : "m³"})</div>
      <svg viewBox="0 0 ${W} ${H}"><polygon points="${band}" fill="rgba(33,102,172,0.2)"/><path d="${line}" stroke="#2166ac" fill="none" stroke-width="2"/>
      <line x1="${pad}" x2="${W - 8}" y1="${Y(0)}" y2="${Y(0)}" stroke="#999"/>
      <text x="2" y="${Y(hi) + 4}" font-size="10">${(hi / unit).toFixed(1)}</text><text x="2" y="${Y(lo)}" font-size="10">${(lo / unit).toFixed(1)}</text>
      <text x="${pad}" y="${H - 4}" font-size="10">${labelOf(S.epochs[0])}</text><text x="${W - 8}" y="${H - 4}" font-size="10" text-anchor="end">${labelOf(S.epochs[S.epochs.length - 1])}</text></svg>`;
  }

  main().then(() => readyResolve(true), (err) => {
    S.errors.push("site: " + (err && err.stack ? err.stack : err));
    status("error: " + err);
    readyReject(err);
  });
})();
