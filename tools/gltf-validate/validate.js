// Validates glTF files with Khronos' glTF validator (npm `gltf-validator`): prints the report's
// counts and every message of severity error or warning, and exits 1 when there is an error.
//   node tools/gltf-validate/validate.js FILE.glb [...]
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

async function check(file) {
  const bytes = new Uint8Array(fs.readFileSync(file));
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 100,
  });
  const issues = report.issues;
  console.log(
    `${file}: ${issues.numErrors} errors, ${issues.numWarnings} warnings, ` +
      `${issues.numInfos} infos, ${issues.numHints} hints`
  );
  for (const m of issues.messages) {
    // Severity 0 is an error, 1 a warning.
    if (m.severity <= 1) {
      console.log(`  ${m.severity === 0 ? "error" : "warning"} ${m.code} at ${m.pointer}: ${m.message}`);
    }
  }
  return issues.numErrors === 0;
}

(async () => {
  const files = process.argv.slice(2);
  if (files.length === 0) {
    console.error("usage: node validate.js FILE.glb [...]");
    process.exit(2);
  }
  let ok = true;
  for (const f of files) {
    ok = (await check(f)) && ok;
  }
  process.exit(ok ? 0 : 1);
})().catch((e) => {
  console.error(e);
  process.exit(2);
});
