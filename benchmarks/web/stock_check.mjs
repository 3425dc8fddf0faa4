// Drive Debian's headless Chromium (software WebGL) through puppeteer-core against the stock CesiumJS page
// (stock_cesium.html) served by a plain static server: per view, set the camera, wait until every tile
// is loaded, count tile requests, screenshot; then sample heights with CesiumJS's own most-detailed
// samplers (sampleTerrainMostDetailed for terrain, scene.sampleHeightMostDetailed for a tileset).
// usage: node stock_check.mjs PAGE_URL CONFIG_JSON SHOT_PREFIX [TIMEOUT_MS]
//   CONFIG: {kind: "terrain"|"tileset", views: [{name, rect: [w,s,e,n]} | {name, lon, lat, height,
//            heading, pitch}], points: [[lon, lat], ...]}   (degrees, metres)
//   prints one JSON line {errors, views: [{name, ms, tileResponses, bad}], heights, wallMs}
import { readFileSync } from "node:fs";
import { openBrowser } from "./browser.mjs";

const [pageUrl, configPath, shotPrefix, timeoutArg] = process.argv.slice(2);
const timeout = Number(timeoutArg || 60000);
const config = JSON.parse(readFileSync(configPath, "utf8"));
const t0 = Date.now();
const out = { errors: [], failedRequests: [], blocked: [], views: [], heights: null };
const browser = await openBrowser(640, 480);
let tileResponses = 0;
const bad = [];
try {
  const page = await browser.context.newPage();
  await page.setViewport({ width: 640, height: 480 });
  await page.setRequestInterception(true);
  const origin = new URL(pageUrl).origin;
  page.on("request", (r) => {
    const u = r.url();
    // the page's own origin, or another loopback server (terralod serve beside the static host)
    const loop = /^http:\/\/(127\.0\.0\.1|localhost)(:\d+)?\//.test(u);
    if (u.startsWith(origin) || loop || u.startsWith("data:") || u.startsWith("blob:")) r.continue();
    else { out.blocked.push(u); r.abort(); }
  });
  page.on("requestfailed", (r) => out.failedRequests.push(r.url() + " " + (r.failure() || {}).errorText));
  page.on("response", (r) => {
    const ok = r.status() === 200 || r.status() === 304;  // 304: the browser's cache revalidated it
    if (/\.(terrain|glb)(\?|$)/.test(r.url())) tileResponses++;
    if (!ok && !r.url().endsWith("/favicon.ico")) bad.push(r.status() + " " + r.url());
  });
  const benign = (t) => /Failed to load resource.*404/.test(t) && !bad.length;  // the favicon a static host lacks
  page.on("pageerror", (e) => out.errors.push("pageerror: " + e.message));
  page.on("console", (m) => { if (m.type() === "error" && !benign(m.text())) out.errors.push("console: " + m.text()); });
  await page.goto(pageUrl, { waitUntil: "load", timeout });
  await page.waitForFunction(() => window.stock && (stock.ready || stock.errors.length), { timeout, polling: 200 });
  // frames drawn since the view was set: "all tiles loaded" means nothing until the scene has drawn a few
  // frames with the new camera (on a busy machine SwiftShader's first frames take seconds, and before any
  // frame the globe has no tile queued, so it reads as loaded)
  await page.evaluate(() => { stock.frames = 0; stock.viewer.scene.postRender.addEventListener(() => { stock.frames++; }); });
  for (const v of config.views) {
    const before = tileResponses;
    const v0 = Date.now();
    await page.evaluate((v) => {
      stock.frames = 0;
      const cam = stock.viewer.camera;
      if (v.rect) cam.setView({ destination: Cesium.Rectangle.fromDegrees(...v.rect) });
      else cam.setView({ destination: Cesium.Cartesian3.fromDegrees(v.lon, v.lat, v.height),
        orientation: { heading: Cesium.Math.toRadians(v.heading || 0), pitch: Cesium.Math.toRadians(v.pitch ?? -90), roll: 0 } });
    }, v);
    // loaded: the globe's (or the tileset's) tiles all loaded on 5 consecutive polls after at least 1 s
    await page.waitForFunction((kind) => {
      const s = stock.viewer.scene;
      s.requestRender();
      const done = stock.frames >= 5 && (kind === "terrain" ? s.globe.tilesLoaded : stock.tileset.tilesLoaded);
      stock.quiet = done ? (stock.quiet || 0) + 1 : 0;
      return stock.quiet >= 5;
    }, { timeout, polling: 200 }, config.kind);
    await page.evaluate(() => { stock.quiet = 0; });
    const ms = Date.now() - v0;
    await page.screenshot({ path: `${shotPrefix}${v.name}.png` });
    out.views.push({ name: v.name, ms, tileResponses: tileResponses - before });
  }
  out.heights = await page.evaluate(async (kind, pts) => {
    const c = pts.map(([lon, lat]) => Cesium.Cartographic.fromDegrees(lon, lat));
    if (kind === "terrain") return (await Cesium.sampleTerrainMostDetailed(stock.terrain, c)).map((p) => p.height);
    return (await stock.viewer.scene.sampleHeightMostDetailed(c)).map((p) => (p.height === undefined ? null : p.height));
  }, config.kind, config.points);
  out.pageErrors = await page.evaluate(() => stock.errors);
} catch (e) {
  out.errors.push("driver: " + e.message);
} finally {
  await browser.close();
}
out.tileResponses = tileResponses;
out.badResponses = bad;
out.wallMs = Date.now() - t0;
console.log(JSON.stringify(out));
