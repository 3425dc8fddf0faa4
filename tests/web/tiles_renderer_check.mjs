// A second, independent 3D Tiles client: 3DTilesRendererJS (npm 3d-tiles-renderer, three.js) loads a
// tileset from a URL with its defaults (errorTarget 16 px), from a camera looking down at the whole tileset
// and then from close above its centre (where the root must refine), until nothing is downloading or parsing.
// usage: node tiles_renderer_check.mjs TILESET_URL [TIMEOUT_MS]
//   prints one JSON line {loaded, failed, errors, triangles, views: [{name, visible, ...}]}
import { PerspectiveCamera, Vector3, Sphere, Mesh } from "three";
import { TilesRenderer } from "3d-tiles-renderer";

const [url, timeoutArg] = process.argv.slice(2);
// the library resolves relative URLs against window.location (it is written for the browser): in Node
// that is the tileset's own URL, nothing more
globalThis.window ??= { location: { href: url } };
globalThis.requestAnimationFrame ??= (f) => setTimeout(() => f(performance.now()), 16);
globalThis.cancelAnimationFrame ??= (id) => clearTimeout(id);
const timeout = Number(timeoutArg || 60000);
const out = { loaded: 0, failed: 0, errors: [], triangles: 0, views: [] };
const tiles = new TilesRenderer(url);
const camera = new PerspectiveCamera(60, 640 / 480, 1, 1e8);
tiles.setCamera(camera);
tiles.setResolution(camera, 640, 480);
tiles.addEventListener("load-model", ({ scene }) => {
  out.loaded++;
  scene.traverse((o) => { if (o instanceof Mesh) out.triangles += (o.geometry.index ? o.geometry.index.count : 0) / 3; });
});
tiles.addEventListener("load-error", ({ error, url: u }) => { out.failed++; out.errors.push(`${u}: ${error && error.message}`); });
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function settle(name) {
  const t0 = Date.now();
  let quiet = 0;
  while (Date.now() - t0 < timeout) {
    camera.updateMatrixWorld();
    tiles.update();
    const s = tiles.stats;
    const busy = (s.downloading || 0) + (s.parsing || 0) + (s.queued || 0);
    quiet = busy === 0 && tiles.root ? quiet + 1 : 0;
    if (quiet > 10) break;
    await sleep(50);
  }
  let visible = 0;
  tiles.group.traverse((o) => { if (o instanceof Mesh && o.visible) visible++; });
  out.views.push({ name, ms: Date.now() - t0, visible, loaded: out.loaded, stats: { ...tiles.stats } });
}

try {
  // first update loads the root tileset; wait for it so the bounding sphere is known
  const t0 = Date.now();
  while (!tiles.root && Date.now() - t0 < timeout) { tiles.update(); await sleep(50); }
  if (!tiles.root) throw new Error("tileset.json never loaded");
  const sphere = new Sphere();
  tiles.getBoundingSphere(sphere);
  const c = sphere.center.clone();
  const up = c.clone().normalize();
  // whole tileset: 2.5 radii out along the local up, looking at the centre
  camera.position.copy(c).addScaledVector(up, sphere.radius * 2.5);
  camera.up.set(0, 0, 1);
  camera.lookAt(c);
  await settle("whole");
  // close: where the root's error projects to 4x the default error target (its children must load)
  // (a root without content, above several roots, is skipped: its children are the drawn roots)
  const r = tiles.root;
  const rootError = r.content && r.content.uri ? r.geometricError : Math.max(...r.children.map((c) => c.geometricError));
  const close = (rootError * 480) / (2 * Math.tan(Math.PI / 6) * 64);
  out.closeDistanceM = close;
  camera.position.copy(c).addScaledVector(up, close + sphere.radius / 20);  // above the mid-height centre
  camera.lookAt(c);
  await settle("close");
} catch (e) {
  out.errors.push("driver: " + e.message);
}
tiles.dispose();
console.log(JSON.stringify(out));
process.exit(0);
