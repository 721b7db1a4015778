#!/usr/bin/env bash
# Builds the npm package `bvhtrace` from crates/web into web/dist/pkg and packs it into
# web/dist/bvhtrace-VERSION.tgz: the wasm bound to JavaScript by wasm-bindgen (with its
# TypeScript declarations), optimised by wasm-opt from npm's binaryen (Debian 12's 108
# breaks wasm-bindgen's reference types), the three.js helpers and the package's README
# and package.json from web/package/, unpacked again into web/dist/packed/package for the
# tests. Then checks the declarations with tsc against a
# program written from the README (web/tests/types.ts). Installs web/package.json's
# devDependencies (npm ci) when they are missing. Honours CARGO_TARGET_DIR.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x web/node_modules/.bin/wasm-opt ] && ! (cd web && npm ci --no-audit --no-fund --loglevel=error); then
  echo "SKIP: npm ci failed (is the npm registry reachable?): the package goes without" \
    "wasm-opt, the tsc check and the three.js example" >&2
fi
npm_tools=0
[ -x web/node_modules/.bin/wasm-opt ] && npm_tools=1
cargo build --release --target wasm32-unknown-unknown -p bvhtrace-web
out=web/dist/pkg
rm -rf "$out"
mkdir -p "$out"
wasm-bindgen --target web --out-dir "$out" \
  "${CARGO_TARGET_DIR:-target}/wasm32-unknown-unknown/release/bvhtrace_web.wasm"
wasm="$out/bvhtrace_web_bg.wasm"
before=$(wc -c < "$wasm")
if [ "$npm_tools" = 1 ]; then
  # -O1: npm's wasm-opt is itself WebAssembly, and its -O3 or -Oz passes took ten minutes
  # here for 0.03% less than -O1's 15 seconds (rustc has optimised the code already).
  web/node_modules/.bin/wasm-opt -O1 "$wasm" -o "$wasm.opt"
  mv "$wasm.opt" "$wasm"
  echo "$wasm: $before bytes from wasm-bindgen, $(wc -c < "$wasm") after wasm-opt -O1"
fi
version=$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -1)
sed "s/@VERSION@/$version/" web/package/package.json > "$out/package.json"
cp web/package/{README.md,three.js,three.d.ts,workers.js,workers.d.ts,worker.js} "$out/"
(cd web/dist && npm pack ./pkg --loglevel=warn)
# What the tests load: the packed files, as `npm install` unpacks them.
rm -rf web/dist/packed
mkdir -p web/dist/packed
tar -xzf "web/dist/bvhtrace-$version.tgz" -C web/dist/packed
echo "packed: $(wc -c < "web/dist/bvhtrace-$version.tgz") bytes, unpacked into web/dist/packed/package"
[ "$npm_tools" = 1 ] || exit 0
# The three.js example page (web/three.html), served from web/dist beside the package
# and three's module, as a project that installed both would import them.
mkdir -p web/dist/three
cp web/node_modules/three/build/three.module.js web/node_modules/three/build/three.core.js \
  web/dist/three/
cp web/three.html web/dist/
# The declarations, as a TypeScript user compiles against them: web/tests/types.ts in a
# project with the packed package in its node_modules, resolved through its exports.
rm -rf web/dist/tsuser
mkdir -p web/dist/tsuser/node_modules
ln -s ../../packed/package web/dist/tsuser/node_modules/bvhtrace
echo '{ "type": "module" }' > web/dist/tsuser/package.json
cp web/tests/types.ts web/dist/tsuser/index.ts
web/node_modules/.bin/tsc -p web/tests/tsconfig.json
echo "tsc: web/tests/types.ts compiles against the package's declarations"
