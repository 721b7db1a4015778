#!/usr/bin/env bash
# Builds bvhtrace for the browser into web/dist: the library (bvhtrace_web.js and its
# wasm, used by index.html) and the viewer (bvhtrace_viewer_web.js and its wasm, used by
# viewer.html), both release builds bound to JavaScript by wasm-bindgen (the CLI's version
# must equal the wasm-bindgen crate's in Cargo.lock), and the two pages. When wasm-opt is
# on the PATH and can read the output (`WASM_OPT=0` skips it), the wasm is shrunk with -Oz.
set -euo pipefail
cd "$(dirname "$0")/.."
# One crate per build: the viewer's eframe turns on wgpu features (WebGL) the library leaves out.
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-web
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-viewer-web
mkdir -p web/dist
for crate in bvhtrace_web bvhtrace_viewer_web; do
  wasm-bindgen --target web --no-typescript --out-dir web/dist \
    "target/wasm32-unknown-unknown/release/$crate.wasm"
  wasm="web/dist/${crate}_bg.wasm"
  if [ "${WASM_OPT:-1}" != 0 ] && command -v wasm-opt > /dev/null; then
    if wasm-opt -Oz --all-features "$wasm" -o "$wasm.opt" 2> /dev/null; then
      mv "$wasm.opt" "$wasm"
    else
      rm -f "$wasm.opt"
      echo "wasm-opt could not read $wasm: left as it is"
    fi
  fi
  echo "$wasm: $(wc -c < "$wasm") bytes"
done
cp web/index.html web/viewer.html web/dist/
