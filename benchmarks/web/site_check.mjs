// Drive the change site (any folder or server that serves it) in Debian's headless Chromium through
// puppeteer-core and its window.terralodSite contract. Reads a JSON job on stdin:
//   {url, timeoutMs, shots: prefix, width, height, steps: [{op, args, shot?}]}
// op is a contract function (setEpoch, setSwipe, changeAt, volume, describeChange, describeVolume) or
// "heights" (CesiumJS's sampleHeightMostDetailed at [[lon, lat], ...] on what is shown), "transfer" (the
// bytes fetched so far, by part: cesium, page, json, tiles3d, rasters) or "pixels"
// (RGB of the last screenshot's pixels at the screen positions of [[lon, lat, h], ...]).
// Prints one JSON line: {errors, blocked, failedRequests, readyMs, firstViewMs, renderer, results: [...]}.
import { openBrowser } from "./browser.mjs";

const job = JSON.parse(await new Promise((res) => { let s = ""; process.stdin.on("data", (d) => (s += d)); process.stdin.on("end", () => res(s)); }));
const timeout = job.timeoutMs || 90000;
const out = { errors: [], blocked: [], failedRequests: [], results: [] };
const browser = await openBrowser(job.width || 900, job.height || 600);
try {
  const page = await browser.context.newPage();
  await page.setViewport({ width: job.width || 900, height: job.height || 600 });
  await page.setRequestInterception(true);
  const origin = new URL(job.url).origin;
  page.on("request", (r) => {
    const u = r.url();
    if (u.startsWith(origin) || u.startsWith("data:") || u.startsWith("blob:")) r.continue();
    else { out.blocked.push(u); r.abort(); }
  });
  page.on("requestfailed", (r) => {  // a request CesiumJS cancels (the view moved on) is not a failure
    const why = (r.failure() || {}).errorText || "";
    if (why !== "net::ERR_ABORTED") out.failedRequests.push(r.url() + " " + why);
  });
  page.on("response", (r) => { if (r.status() >= 400) out.failedRequests.push(r.status() + " " + r.url()); });
  page.on("pageerror", (e) => out.errors.push("pageerror: " + e.message));
  page.on("console", (m) => { if (m.type() === "error") out.errors.push("console: " + m.text()); });
  const t0 = Date.now();
  await page.goto(job.url, { waitUntil: "load", timeout });
  await page.waitForFunction(() => window.terralodSite && window.terralodSite.ready, { timeout });
  await page.evaluate(() => window.terralodSite.ready);
  out.readyMs = Date.now() - t0;
  Object.assign(out, await page.evaluate(() => ({ firstViewMs: terralodSite.firstViewMs, epochs: terralodSite.epochs,
    pairs: terralodSite.pairs, renderer: (() => { const gl = terralodSite.viewer.scene.context._gl; const ext = gl.getExtension("WEBGL_debug_renderer_info"); return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER); })() })));
  for (const step of job.steps || []) {
    const t1 = Date.now();
    let value;
    if (step.op === "heights") {
      value = await page.evaluate(async (pts) => {
        const v = terralodSite.viewer;
        const got = await v.scene.sampleHeightMostDetailed(pts.map(([lo, la]) => Cesium.Cartographic.fromDegrees(lo, la)), [], 1.0);
        return got.map((c) => (c && Number.isFinite(c.height) ? c.height : null));
      }, step.args[0]);
    } else if (step.op === "screen") {
      value = await page.evaluate((pts) => pts.map(([lo, la, h]) => {
        const p = Cesium.SceneTransforms.worldToWindowCoordinates(terralodSite.viewer.scene, Cesium.Cartesian3.fromDegrees(lo, la, h));
        return p ? [p.x, p.y] : null;
      }), step.args[0]);
    } else if (step.op === "camera") {
      value = await page.evaluate(async ([lon, lat, h, heading, pitch]) => {
        terralodSite.viewer.camera.setView({ destination: Cesium.Cartesian3.fromDegrees(lon, lat, h),
          orientation: { heading: Cesium.Math.toRadians(heading), pitch: Cesium.Math.toRadians(pitch), roll: 0 } });
        await new Promise((r) => setTimeout(r, 300));
        await new Promise((r) => { const c = () => (terralodSite.tilesets.every((t) => !t.show || t.tilesLoaded) ? r() : setTimeout(c, 100)); c(); });
        return true;
      }, step.args);
    } else if (step.op === "dom") {  // what a visitor sees besides the globe
      value = await page.evaluate(() => {
        const $ = (id) => document.getElementById(id);
        const path = $("chart").querySelector("path");
        return { play: !$("play").hidden, legend: !$("legend").hidden, legendText: $("legend").innerText,
          chartPoints: path ? (path.getAttribute("d").match(/[ML]/g) || []).length : 0, summary: $("summary").innerText,
          north: !!$("north-needle"), scale: $("scale-text").textContent };
      });
    } else if (step.op === "transfer") {  // bytes fetched so far (resource timing's body sizes), by part
      value = await page.evaluate(() => {
        const parts = { cesium: 0, page: 0, tiles3d: 0, rasters: 0, json: 0 }, count = { ...parts };
        let largest = 0;
        for (const e of performance.getEntriesByType("resource").concat(performance.getEntriesByType("navigation"))) {
          const p = new URL(e.name).pathname, b = e.encodedBodySize || 0;
          const k = p.startsWith("/cesium/") ? "cesium" : p.startsWith("/epochs/") && !p.endsWith(".json") ? "tiles3d"
            : p.startsWith("/pairs/") && !p.endsWith(".json") ? "rasters" : p.endsWith(".json") ? "json" : "page";
          parts[k] += b; count[k] += 1; largest = Math.max(largest, b);
        }
        return { bytes: parts, files: count, largest };
      });
    } else if (step.op === "press") {  // a button of the page, by id
      await page.click("#" + step.args[0]);
      await new Promise((r) => setTimeout(r, 300));
      value = await page.evaluate(() => document.getElementById("answer").textContent);
    } else if (step.op === "click") {
      await page.mouse.click(step.args[0], step.args[1]);
      await new Promise((r) => setTimeout(r, 800));
      value = await page.evaluate(() => document.getElementById("answer").textContent);
    } else {
      value = await page.evaluate(async (op, args) => await terralodSite[op](...args), step.op, step.args || []);
    }
    const r = { op: step.op, ms: Date.now() - t1, value };
    if (step.shot) {
      await new Promise((res) => setTimeout(res, step.settleMs || 400));
      await page.screenshot({ path: `${job.shots}${step.shot}.png` });
      r.shot = `${job.shots}${step.shot}.png`;
    }
    out.results.push(r);
  }
  Object.assign(out, await page.evaluate(() => ({ pageErrors: terralodSite.errors })));
  out.errors.push(...out.pageErrors);
} catch (e) {
  out.errors.push("driver: " + (e && e.message));
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
