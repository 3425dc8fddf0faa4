// Drive Debian's headless Chromium (software WebGL) through puppeteer-core against a running
// `terralod serve`: load the viewer in one format, wait for every tile, sample heights, take a screenshot.
// usage: node browser_check.mjs URL FORMATS POINTS_JSON SCREENSHOT_PREFIX [TIMEOUT_MS]
//   FORMATS: comma-separated (terrain,3dtiles), each loaded in its own browser, concurrently;
//   writes PREFIX<format>.png and prints one JSON line {format: result, ...} on stdout.
import puppeteer from "puppeteer-core";

const [url, formats, pointsJson, shotPrefix, timeoutArg] = process.argv.slice(2);
const timeout = Number(timeoutArg || 40000);
const points = JSON.parse(pointsJson);
const launch = () => puppeteer.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  headless: "new",
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--window-size=640,480",
    "--disable-background-timer-throttling", "--disable-renderer-backgrounding", "--disable-backgrounding-occluded-windows"],
});
async function check(format) {
const browser = await launch();  // one browser per format: a background tab of a shared one gets no frames
const shot = `${shotPrefix}${format}.png`;
const out = { format, errors: [], failedRequests: [], blocked: [], tileResponses: 0, badTileResponses: [] };
try {
  const page = await browser.newPage();
  await page.setViewport({ width: 640, height: 480 });
  await page.setRequestInterception(true);
  const origin = new URL(url).origin;
  page.on("request", (r) => {
    const u = r.url();
    if (u.startsWith(origin) || u.startsWith("data:") || u.startsWith("blob:")) r.continue();
    else { out.blocked.push(u); r.abort(); }
  });
  page.on("requestfailed", (r) => out.failedRequests.push(r.url() + " " + (r.failure() || {}).errorText));
  page.on("response", (r) => {
    const u = r.url();
    if (/\.(terrain|glb)(\?|$)/.test(u)) { out.tileResponses++; if (r.status() !== 200) out.badTileResponses.push(r.status() + " " + u); }
  });
  page.on("pageerror", (e) => out.errors.push("pageerror: " + e.message));
  page.on("console", (m) => { if (m.type() === "error") out.errors.push("console: " + m.text()); });
  const t0 = Date.now();
  await page.goto(`${url}?format=${format}`, { waitUntil: "load", timeout });
  await page.waitForFunction(() => window.terralod && (window.terralod.loaded || window.terralod.errors.length), { timeout, polling: 200 });
  out.loadMs = Date.now() - t0;
  await page.evaluate(() => terralod.viewer && terralod.viewer.scene.requestRender());
  await new Promise((r) => setTimeout(r, 500));
  const state = await page.evaluate(() => ({ loaded: terralod.loaded, errors: terralod.errors, tiles: terralod.tiles,
    triangles: terralod.triangles, firstFrameMs: terralod.firstFrameMs, loadedMs: terralod.loadedMs }));
  Object.assign(out, state, { errors: out.errors.concat(state.errors) });
  out.heights = await page.evaluate(async (pts) => await terralod.sample(pts), points);
  await new Promise((r) => setTimeout(r, 300));
  await page.screenshot({ path: shot });
  out.hud = await page.evaluate(() => document.getElementById("hud").innerText);
  await page.mouse.move(320, 330);
  await page.mouse.move(322, 332);
  await new Promise((r) => setTimeout(r, 400));
  out.cursor = await page.evaluate(() => document.getElementById("cursor").textContent);
} catch (e) {
  out.errors.push("driver: " + e.message);
} finally {
  await browser.close();
}
return out;
}
const t0 = Date.now();
const results = await Promise.all(formats.split(",").map(check));
const all = Object.fromEntries(results.map((r) => [r.format, r]));
all.wallMs = Date.now() - t0;
console.log(JSON.stringify(all));
