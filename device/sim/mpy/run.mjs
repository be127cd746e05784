// Run a script on real MicroPython (the WebAssembly port, npm
// @micropython/micropython-webassembly-pyscript) under Node.
//
//   node device/sim/mpy/run.mjs [--lib DIR]... [--put HOST=MP]... [--heap BYTES] SCRIPT.py [ARG]...
//
// --lib DIR   copy DIR's .py files (and sub-packages) into /lib, which is on sys.path
// --put H=M   copy the host file H into MicroPython's filesystem at M (for input streams)
// --heap N    MicroPython heap in bytes (default 262144, an RP2040-class budget)
// The script reads its arguments as mpy_args.ARGV (sys.argv is read-only there).
// The script's stdout/stderr pass through. Exit status: 0, or 1 on an uncaught
// Python exception (its traceback goes to stderr), or 2 on a usage error.
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript";
import fs from "node:fs";
import path from "node:path";

const argv = process.argv.slice(2);
const libs = [], puts = [];
let heap = 262144, script = null, args = [];
for (let i = 0; i < argv.length; i++) {
  const a = argv[i];
  if (a === "--lib") libs.push(argv[++i]);
  else if (a === "--put") puts.push(argv[++i]);
  else if (a === "--heap") heap = parseInt(argv[++i], 10);
  else { script = a; args = argv.slice(i + 1); break; }
}
if (!script || !Number.isFinite(heap)) {
  process.stderr.write("usage: run.mjs [--lib DIR]... [--put HOST=MP]... [--heap BYTES] SCRIPT.py [ARG]...\n");
  process.exit(2);
}

const mp = await loadMicroPython({
  heapsize: heap,
  linebuffer: false,
  stdout: (s) => process.stdout.write(s),
  stderr: (s) => process.stderr.write(s),
});

function mkdirs(p) {
  let cur = "";
  for (const part of p.split("/").filter(Boolean)) {
    cur += "/" + part;
    try { mp.FS.mkdir(cur); } catch (e) { /* exists */ }
  }
}

function copyTree(src, dst) {
  mkdirs(dst);
  for (const ent of fs.readdirSync(src, { withFileTypes: true })) {
    const s = path.join(src, ent.name);
    if (ent.isDirectory()) {
      if (ent.name === "__pycache__" || ent.name.startsWith(".")) continue;
      copyTree(s, dst + "/" + ent.name);
    } else if (ent.name.endsWith(".py")) {
      mp.FS.writeFile(dst + "/" + ent.name, fs.readFileSync(s));
    }
  }
}

mkdirs("/lib");
for (const d of libs) copyTree(d, "/lib");
for (const p of puts) {
  const k = p.indexOf("=");
  if (k < 0) { process.stderr.write(`--put needs HOST=MP, got ${p}\n`); process.exit(2); }
  const mpPath = p.slice(k + 1);
  mkdirs(path.posix.dirname(mpPath));
  mp.FS.writeFile(mpPath, fs.readFileSync(p.slice(0, k)));
}

const code = fs.readFileSync(script, "utf8");
// MicroPython's sys.argv cannot be assigned here: the arguments go in a module
mp.FS.writeFile("/lib/mpy_args.py", "ARGV = " + JSON.stringify([script, ...args]) + "\n");
const pre = "import sys\nsys.path.insert(0, '/lib')\n";
try {
  mp.runPython(pre);
  mp.runPython(code);
} catch (e) {
  process.stderr.write(String(e && e.message ? e.message : e) + "\n");
  process.exit(1);
}
process.exit(0);
