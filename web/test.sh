#!/usr/bin/env bash
# The browser test: builds the wasm (web/build.sh), serves it on 127.0.0.1 to headless
# Chromium (WebGPU on SwiftShader), traces a fixed camera's rays there and checks every hit
# against the CPU twin's, bit for bit. Prints `browser parity: N hits, 0 differ`; exits
# non-zero on any difference or page error.
set -euo pipefail
cd "$(dirname "$0")/.."
web/build.sh
cargo run --release -q -p bvhtrace-integration --example browser_parity -- web/dist "$@"
