// Validate one .glb with the Khronos glTF-Validator; print its JSON report on stdout.
// Usage: node tests/gltf/validate.mjs FILE.glb   (exit 0 when the report was made, whatever it says)
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

const file = process.argv[2];
const bytes = new Uint8Array(await readFile(file));
const report = await validator.validateBytes(bytes, {
  uri: file,
  maxIssues: 0, // report every issue
  externalResourceFunction: (uri) => Promise.reject(new Error(`no external resources expected: ${uri}`)),
});
process.stdout.write(JSON.stringify(report, null, 1) + "\n");
