// A second, independent quantized-mesh client: loaders.gl (npm @loaders.gl/terrain) decodes every
// .terrain tile of an export folder, as a user of deck.gl / loaders.gl would.
// usage: node qm_decode.mjs EXPORT_DIR OUT_JSON
//   OUT_JSON: {tiles: {"z/x/y": {header, u, v, height, indices, west, south, east, north, normals, watermask}}}
//   (u/v: the tile's 0..32767 lattice from the decoder; height: loaders.gl's POSITION z, metres)
import { readFileSync, readdirSync, statSync, writeFileSync } from "node:fs";
import { join, relative } from "node:path";
import { createRequire } from "node:module";
import { pathToFileURL } from "node:url";
import { parse } from "@loaders.gl/core";
import { QuantizedMeshLoader } from "@loaders.gl/terrain";

const [dir, outPath] = process.argv.slice(2);
// the loader's own decoder (header, edge lists, extensions), which its public parse does not return
const require = createRequire(import.meta.url);
const pkg = require.resolve("@loaders.gl/terrain").replace(/index\.(c?js)$/, "lib/decode-quantized-mesh.js");
const { default: decode } = await import(pathToFileURL(pkg).href);

function* walk(d) {
  for (const name of readdirSync(d)) {
    const p = join(d, name);
    if (statSync(p).isDirectory()) yield* walk(p);
    else if (name.endsWith(".terrain")) yield p;
  }
}
const out = { tiles: {}, errors: [] };
for (const f of walk(dir)) {
  const key = relative(dir, f).replace(/\.terrain$/, "").split(/[\\/]/).join("/");
  const [z, x, y] = key.split("/").map(Number);
  const d = 180 / 2 ** z;
  const bounds = [-180 + x * d, -90 + y * d, -180 + (x + 1) * d, -90 + (y + 1) * d];
  try {
    const buf = readFileSync(f);
    const ab = buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength);
    const mesh = await parse(ab, QuantizedMeshLoader, { "quantized-mesh": { bounds }, worker: false });
    const raw = decode(ab.slice(0));
    const n = raw.vertexData.length / 3;
    const pos = mesh.attributes.POSITION.value;
    const height = new Array(n);
    for (let i = 0; i < n; i++) height[i] = pos[3 * i + 2];
    out.tiles[key] = {
      header: raw.header,
      u: Array.from(raw.vertexData.subarray(0, n)),
      v: Array.from(raw.vertexData.subarray(n, 2 * n)),
      height,
      indices: Array.from(mesh.indices.value),
      west: Array.from(raw.westIndices), south: Array.from(raw.southIndices),
      east: Array.from(raw.eastIndices), north: Array.from(raw.northIndices),
      normals: raw.extensions.vertexNormals ? raw.extensions.vertexNormals.length : 0,
      watermask: raw.extensions.waterMask ? raw.extensions.waterMask.byteLength : 0,
      bytes: buf.length,
    };
  } catch (e) {
    out.errors.push(`${key}: ${e.message}`);
  }
}
writeFileSync(outPath, JSON.stringify(out));
console.log(JSON.stringify({ tiles: Object.keys(out.tiles).length, errors: out.errors.length }));
