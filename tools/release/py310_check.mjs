// Python 3.10 check on Pyodide 0.22.1 (CPython 3.10.2 in WebAssembly, from the npm registry):
// every .py file compiles with the 3.10 grammar, spiel_edge.compat falls back to tomli, the
// built-in profile parses. Run through tools/release/py310_check.sh (no numpy there: no test suite).
import fs from "fs";
import path from "path";
const { loadPyodide } = await import(path.resolve(process.env.PYODIDE_DIR, "package/pyodide.mjs"));
const [repo, tomliDir] = process.argv.slice(2);
const py = await loadPyodide({ indexURL: path.resolve(process.env.PYODIDE_DIR, "package") + "/" });
const files = [];
function walk(dir, rel) {
  for (const e of fs.readdirSync(dir, { withFileTypes: true })) {
    if (e.name.startsWith(".") || e.name === "__pycache__" || e.name.endsWith(".egg-info")) continue;
    const p = path.join(dir, e.name), r = rel ? rel + "/" + e.name : e.name;
    if (e.isDirectory()) walk(p, r); else if (e.name.endsWith(".py") || e.name.endsWith(".toml")) files.push([p, r]);
  }
}
for (const top of ["spiel_edge", "firmware_protocol", "tools", "tests"]) walk(path.join(repo, top), top);
for (const [p, r] of files) {
  py.FS.mkdirTree("/src/" + path.dirname(r));
  py.FS.writeFile("/src/" + r, fs.readFileSync(p));
}
py.FS.mkdirTree("/src/tomli");
for (const f of fs.readdirSync(tomliDir)) if (f.endsWith(".py")) py.FS.writeFile("/src/tomli/" + f, fs.readFileSync(path.join(tomliDir, f)));
const out = py.runPython(`
import sys, py_compile, pathlib, json
sys.path.insert(0, "/src")
bad = []
n = 0
for f in sorted(pathlib.Path("/src").rglob("*.py")):
    if f.parts[2] == "tomli": continue
    n += 1
    try:
        py_compile.compile(str(f), doraise=True)
    except py_compile.PyCompileError as e:
        bad.append(str(e).splitlines()[-1][:200])
from spiel_edge.compat import tomllib
profile = tomllib.loads(pathlib.Path("/src/spiel_edge/profile/builtin/spiel-icra23.toml").read_text())
json.dumps({"python": sys.version.split()[0], "compiled": n, "syntax_errors": bad, "tomllib": tomllib.__name__, "profile_sections": sorted(profile)})
`);
console.log(out);
