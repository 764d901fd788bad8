#!/usr/bin/env bash
# Python 3.10 check without a 3.10 interpreter from apt (Debian has none) or pip (none there):
# Pyodide 0.22.1 from the npm registry is CPython 3.10.2 in WebAssembly, run by node.
#   bash tools/release/py310_check.sh [WORKDIR]      (needs node and npm; prints one JSON line)
# Compiles every .py file of the checkout with the 3.10 grammar and imports spiel_edge.compat
# (tomli fallback, taken from pip's vendored copy). numpy is not in Pyodide's npm package, so
# the test suite cannot run there.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
WORK=${1:-/var/tmp/spiel-py310}
mkdir -p "$WORK"
if [ ! -e "$WORK/package/pyodide.mjs" ]; then
    (cd "$WORK" && npm pack --silent pyodide@0.22.1 >/dev/null && tar xzf pyodide-0.22.1.tgz \
        && npm install --silent --no-audit --no-fund ws node-fetch@2 >/dev/null)
fi
PY=${SPIEL_HOST_PYTHON:-$REPO/.venv/bin/python}
TOMLI=$("$PY" -c 'import pip._vendor.tomli as t, os; print(os.path.dirname(t.__file__))')
cd "$WORK" && PYODIDE_DIR="$WORK" node "$REPO/tools/release/py310_check.mjs" "$REPO" "$TOMLI"
