// Run the Khronos glTF validator on every .glb under a folder: one JSON line {files, errors, warnings, messages}.
import fs from "fs";
import path from "path";
import { createRequire } from "module";
const require = createRequire(import.meta.url);
const validator = require("gltf-validator");
const files = [];
const walk = (d) => { for (const f of fs.readdirSync(d)) { const p = path.join(d, f); if (fs.statSync(p).isDirectory()) walk(p); else if (p.endsWith(".glb")) files.push(p); } };
walk(process.argv[2]);
let errors = 0, warnings = 0;
const messages = new Set();
for (const f of files) {
  const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)), { maxIssues: 50 });
  errors += r.issues.numErrors; warnings += r.issues.numWarnings;
  for (const m of r.issues.messages) if (m.severity <= 1) messages.add(`${m.code}: ${m.message}`);
}
console.log(JSON.stringify({ files: files.length, errors, warnings, messages: [...messages].slice(0, 10) }));
