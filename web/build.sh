#!/usr/bin/env bash
# Builds bvhtrace for the browser into web/dist: the library (bvhtrace_web.js and its
# wasm, used by index.html) and the viewer (bvhtrace_viewer_web.js and its wasm, used by
# viewer.html), both release builds bound to JavaScript by wasm-bindgen (the CLI's version
# must equal the wasm-bindgen crate's in Cargo.lock), and the two pages. `WASM_OPT=1` also
# shrinks the wasm with wasm-opt -Oz: it needs binaryen 116 or later (Debian 12's 108
# breaks wasm-bindgen's externref table; the page then fails to instantiate).
set -euo pipefail
cd "$(dirname "$0")/.."
# One crate per build, so that neither gets the other's dependencies' features.
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-web --features one-shot
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-viewer-web
mkdir -p web/dist
for crate in bvhtrace_web bvhtrace_viewer_web; do
  wasm-bindgen --target web --no-typescript --out-dir web/dist \
    "${CARGO_TARGET_DIR:-target}/wasm32-unknown-unknown/release/$crate.wasm"
  wasm="web/dist/${crate}_bg.wasm"
  if [ "${WASM_OPT:-0}" = 1 ]; then
    wasm-opt -Oz --all-features "$wasm" -o "$wasm.opt"
    mv "$wasm.opt" "$wasm"
  fi
  echo "$wasm: $(wc -c < "$wasm") bytes"
done
cp web/index.html web/viewer.html web/dist/
