// Validate glTF/GLB files with the Khronos glTF validator (npm: gltf-validator).
// Usage: node scripts/validate_gltf.mjs FILE...  -> one JSON line per file: {file, errors, warnings, infos, hints, messages}
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const file of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(file)));
  const i = report.issues;
  const messages = i.messages.map((m) => `${m.severity} ${m.code} ${m.pointer ?? ""} ${m.message}`);
  console.log(JSON.stringify({ file, errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos,
                               hints: i.numHints, messages }));
}
