#!/usr/bin/env bash
# Serves web/dist (after web/build.sh) on http://127.0.0.1:PORT/ (default 8000): open
# index.html (the library example) or viewer.html (the viewer) in a browser with WebGPU.
set -euo pipefail
cd "$(dirname "$0")/.."
exec cargo run --release -q -p bvhtrace-integration --example serve -- web/dist "${1:-8000}"
