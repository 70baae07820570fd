// Validates GLB files with the Khronos glTF Validator and prints one JSON report per line:
// {"file": ..., "errors": N, "warnings": N, "messages": [...]}.
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, { maxIssues: 50 });
  const issues = report.issues;
  console.log(JSON.stringify({
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    messages: issues.messages.map((m) => `${m.severity === 0 ? "error" : "note"} ${m.code} ${m.pointer ?? ""}: ${m.message}`),
  }));
}
