// terralod viewer: CesiumJS with no account, token or internet (baseLayer: false), the store's terrain as
// quantized-mesh (?format=terrain, default) or 3D Tiles (?format=3dtiles), hypsometric colours + hillshade,
// tile / triangle counts, the height under the cursor and, for a store with epochs, an epoch slider with
// the change overlay. window.terralod is the hook the browser tests use.
"use strict";
(async function () {
  const status = (t) => { document.getElementById("status").textContent = t; };
  const T = (window.terralod = { errors: [], ready: false, loaded: false, format: "terrain", tiles: 0, triangles: 0 });
  if (typeof Cesium === "undefined") {
    status("CesiumJS is not installed on the server: run `npm ci` in the terralod repository (bash scripts/install.sh does), then restart terralod serve");
    T.errors.push("CesiumJS missing");
    return;
  }
  window.addEventListener("error", (e) => T.errors.push(String(e.message)));
  const params = new URLSearchParams(location.search);
  const format = params.get("format") === "3dtiles" ? "3dtiles" : "terrain";
  T.format = format;
  const info = await (await fetch("/info.json")).json();
  T.info = info;
  const epochs = info.epochs || [];
  let epoch = epochs.includes(params.get("epoch")) ? params.get("epoch") : info.epoch;
  const prefix = (ep) => (epochs.length && ep ? `/e/${encodeURIComponent(ep)}` : "");
  const makeTerrain = async (ep) => {
    const p = await Cesium.CesiumTerrainProvider.fromUrl(prefix(ep) + "/terrain/", { requestVertexNormals: true, requestWaterMask: false, requestMetadata: false });
    p.errorEvent.addEventListener((err) => T.errors.push("terrain: " + (err.message || err)));
    return p;
  };
  const [w, s, e, n] = info.bounds_deg;
  const [zlo, zhi] = info.elevation_range_m;

  // hypsometric ramp (green lowlands → brown → white peaks)
  const stops = [[0.0, [46, 110, 60]], [0.25, [120, 160, 80]], [0.5, [200, 180, 110]], [0.75, [150, 105, 70]], [1.0, [245, 245, 245]]];
  const ramp = document.createElement("canvas");
  ramp.width = 256; ramp.height = 1;
  const g = ramp.getContext("2d");
  const grad = g.createLinearGradient(0, 0, 256, 0);
  for (const [t, c] of stops) grad.addColorStop(t, `rgb(${c.join(",")})`);
  g.fillStyle = grad; g.fillRect(0, 0, 256, 1);

  const opts = {
    baseLayer: false, baseLayerPicker: false, geocoder: false, timeline: false, animation: false,
    homeButton: false, sceneModePicker: false, navigationHelpButton: false, fullscreenButton: false,
    infoBox: false, selectionIndicator: false, requestRenderMode: true, maximumRenderTimeChange: Infinity, skyBox: false,
    contextOptions: { webgl: { preserveDrawingBuffer: true } },
  };
  let terrainProvider = null;
  if (format === "terrain") {
    terrainProvider = await makeTerrain(epoch);
    opts.terrainProvider = terrainProvider;
  }
  const viewer = new Cesium.Viewer("globe", opts);
  T.viewer = viewer;
  const scene = viewer.scene, globe = scene.globe;
  scene.skyAtmosphere.show = false;
  scene.fog.enabled = false;
  globe.baseColor = Cesium.Color.fromCssColorString("#223");
  globe.showGroundAtmosphere = false;
  globe.depthTestAgainstTerrain = true;
  globe.maximumScreenSpaceError = 2;

  // hillshade: a fixed light from the north-west, 45° up, at the terrain's centre
  const centre = Cesium.Cartesian3.fromDegrees((w + e) / 2, (s + n) / 2, (zlo + zhi) / 2);
  const enu = Cesium.Transforms.eastNorthUpToFixedFrame(centre);
  const toLight = Cesium.Matrix4.multiplyByPointAsVector(enu, new Cesium.Cartesian3(-0.5, 0.5, 0.7071), new Cesium.Cartesian3());
  scene.light = new Cesium.DirectionalLight({ direction: Cesium.Cartesian3.normalize(Cesium.Cartesian3.negate(toLight, new Cesium.Cartesian3()), new Cesium.Cartesian3()), intensity: 2.2 });

  let tileset = null;
  if (format === "terrain") {
    globe.enableLighting = true;
    globe.dynamicAtmosphereLighting = false;
    globe.material = Cesium.Material.fromType("ElevationRamp", { image: ramp, minimumHeight: zlo, maximumHeight: zhi });
  } else {
    tileset = await makeTileset(epoch);
    T.tileset = tileset;
    globe.show = false;
  }
  async function makeTileset(ep) {
    const ts = await Cesium.Cesium3DTileset.fromUrl(prefix(ep) + "/3dtiles/tileset.json", { maximumScreenSpaceError: 2 });
    ts.tileFailed.addEventListener((err) => T.errors.push("3dtiles: " + err.url + ": " + err.message));
    const up = Cesium.Cartesian3.normalize(centre, new Cesium.Cartesian3());
    ts.customShader = new Cesium.CustomShader({
      lightingModel: Cesium.LightingModel.PBR,
      uniforms: {
        u_ramp: { type: Cesium.UniformType.SAMPLER_2D, value: new Cesium.TextureUniform({ url: ramp.toDataURL() }) },
        u_centre: { type: Cesium.UniformType.VEC3, value: centre },
        u_up: { type: Cesium.UniformType.VEC3, value: up },
        u_range: { type: Cesium.UniformType.VEC2, value: new Cesium.Cartesian2(zlo, zhi) },
      },
      fragmentShaderText: `
        void fragmentMain(FragmentInput fsInput, inout czm_modelMaterial material) {
          float h = (u_range.x + u_range.y) * 0.5 + dot(fsInput.attributes.positionWC - u_centre, u_up);
          float t = clamp((h - u_range.x) / max(u_range.y - u_range.x, 1.0), 0.0, 1.0);
          material.diffuse = texture(u_ramp, vec2(t, 0.5)).rgb;
        }`,
    });
    scene.primitives.add(ts);
    if (T.onTileset) T.onTileset(ts);
    return ts;
  }

  // epochs (a store with epochs): the slider switches the terrain to that epoch and drapes the change
  // since the first epoch over it (red up, blue down)
  const rect = Cesium.Rectangle.fromDegrees(w, s, e, n);
  let overlay = null;
  const showChange = (ep) => {
    if (overlay) { viewer.entities.remove(overlay); overlay = null; }
    if (!epochs.length || ep === epochs[0]) return;
    overlay = viewer.entities.add({ rectangle: { coordinates: rect, classificationType: format === "terrain" ? Cesium.ClassificationType.TERRAIN : Cesium.ClassificationType.CESIUM_3D_TILE,
      material: new Cesium.ImageMaterialProperty({ image: `/change/${encodeURIComponent(epochs[0])}/${encodeURIComponent(ep)}.png`, transparent: true }) } });
  };
  T.setEpoch = async (ep) => {
    epoch = ep;
    document.getElementById("epochname").textContent = `${ep} (change since ${epochs[0]})`;
    T.loaded = false;
    if (format === "terrain") { terrainProvider = await makeTerrain(ep); viewer.terrainProvider = terrainProvider; }
    else { scene.primitives.remove(tileset); tileset = T.tileset = await makeTileset(ep); tileset.allTilesLoaded.addEventListener(done); }
    showChange(ep);
    scene.requestRender();
  };
  if (epochs.length) {
    const box = document.getElementById("epochs"), slider = document.getElementById("epoch");
    box.hidden = false; slider.max = epochs.length - 1; slider.value = Math.max(0, epochs.indexOf(epoch));
    document.getElementById("epochname").textContent = `${epoch} (change since ${epochs[0]})`;
    slider.addEventListener("change", () => T.setEpoch(epochs[+slider.value]));
    showChange(epoch);
  }

  // camera: an oblique view of the whole terrain
  const diag = Cesium.Cartesian3.distance(Cesium.Cartesian3.fromDegrees(w, s, zlo), Cesium.Cartesian3.fromDegrees(e, n, zlo));
  viewer.camera.lookAt(centre, new Cesium.HeadingPitchRange(0.0, Cesium.Math.toRadians(-50), 0.95 * diag));
  viewer.camera.lookAtTransform(Cesium.Matrix4.IDENTITY);

  // counts
  const counts = () => {
    let tiles = 0, tris = 0;
    if (tileset) {
      tiles = tileset.statistics.selected || 0;
      tris = tileset.statistics.numberOfTrianglesSelected || 0;
    } else {
      const list = (globe._surface && globe._surface._tilesToRender) || [];
      tiles = list.length;
      for (const t of list) {
        const m = t.data && t.data.renderedMesh;
        if (m && m.indices) tris += m.indices.length / 3;
      }
    }
    T.tiles = tiles; T.triangles = tris;
    document.getElementById("counts").textContent = `tiles ${tiles} · triangles ${tris.toLocaleString()}`;
  };
  scene.postRender.addEventListener(counts);

  // height under the cursor
  const handler = new Cesium.ScreenSpaceEventHandler(scene.canvas);
  handler.setInputAction((mv) => {
    let c = null;
    if (scene.pickPositionSupported) {
      const p = scene.pickPosition(mv.endPosition);
      if (Cesium.defined(p)) c = Cesium.Cartographic.fromCartesian(p);
    }
    document.getElementById("cursor").textContent = c ? `height under cursor ${c.height.toFixed(1)} m (${Cesium.Math.toDegrees(c.latitude).toFixed(5)}, ${Cesium.Math.toDegrees(c.longitude).toFixed(5)})` : "height under cursor –";
  }, Cesium.ScreenSpaceEventType.MOUSE_MOVE);

  // heights for the tests: most detailed terrain / tiles at lon, lat (degrees)
  T.sample = async (pts) => {
    const carto = pts.map(([lo, la]) => Cesium.Cartographic.fromDegrees(lo, la));
    if (terrainProvider) {
      const out = await Cesium.sampleTerrainMostDetailed(terrainProvider, carto);
      return out.map((c) => c.height);
    }
    const out = await scene.sampleHeightMostDetailed(carto, [], 1.0);
    return out.map((c) => (c && Number.isFinite(c.height) ? c.height : null));
  };

  T.t0 = performance.now();
  function done() { if (!T.loaded) { T.loaded = true; T.loadedMs = performance.now() - T.t0; status("all tiles loaded"); } }
  scene.postRender.addEventListener(() => { if (T.firstFrameMs === undefined) T.firstFrameMs = performance.now() - T.t0; });
  if (tileset) tileset.allTilesLoaded.addEventListener(done);
  else globe.tileLoadProgressEvent.addEventListener((q) => { if (q === 0 && globe.tilesLoaded) done(); });
  T.ready = true;
  status("loading tiles…");
})().catch((err) => { (window.terralod = window.terralod || { errors: [] }).errors.push("viewer: " + (err && err.stack || err)); document.getElementById("status").textContent = "error: " + err; });
