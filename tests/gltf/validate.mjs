// Validates one .glb with the Khronos glTF validator (installed by scripts/setup_node.sh
// into .tools/node). Prints the report as JSON on stdout; exit code 0 = no errors,
// 1 = the validator reported errors, 2 = it could not run (missing validator or file).
//
// usage: node tests/gltf/validate.mjs FILE.glb
import { readFile } from 'node:fs/promises';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';
import path from 'node:path';

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '..', '..');
const file = process.argv[2];
if (!file) {
  console.error('usage: node tests/gltf/validate.mjs FILE.glb');
  process.exit(2);
}

// The validator lives outside any node_modules on this script's path, so resolve it
// explicitly from the install prefix instead of relying on Node's lookup.
let validator;
try {
  const require = createRequire(path.join(root, '.tools', 'node', 'package.json'));
  validator = require('gltf-validator');
} catch (e) {
  console.error(`gltf-validator is not installed (${e.message}); run: bash scripts/setup_node.sh`);
  process.exit(2);
}

let bytes;
try {
  bytes = new Uint8Array(await readFile(file));
} catch (e) {
  console.error(`cannot read ${file}: ${e.message}`);
  process.exit(2);
}

// A .glb is self-contained: any external resource request is itself a finding.
const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 0,
  externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
});
console.log(JSON.stringify(report, null, 2));
process.exit(report.issues.numErrors > 0 ? 1 : 0);
