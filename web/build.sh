#!/usr/bin/env bash
# Builds bvhtrace-web for the browser: the wasm (release), bound to JavaScript by
# wasm-bindgen (the CLI's version must equal the wasm-bindgen crate's in Cargo.lock), into
# web/dist (bvhtrace_web.js, bvhtrace_web_bg.wasm). Not run through wasm-opt: Debian 12's
# (binaryen 108) breaks wasm-bindgen's externref table.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-web
wasm-bindgen --target web --no-typescript --out-dir web/dist \
  target/wasm32-unknown-unknown/release/bvhtrace_web.wasm
echo "web/dist: $(wc -c < web/dist/bvhtrace_web_bg.wasm) bytes of wasm"
