#!/usr/bin/env bash
# The browser test: builds the wasm (web/build.sh), serves it on 127.0.0.1 to headless
# Chromium, and checks two pages:
#  - the library: a fixed camera's rays traced on WebGPU (SwiftShader), every hit against
#    the CPU twin's, bit for bit: prints `browser parity: N hits, 0 differ`; then the BVH
#    built on WebGPU (gpu-ploc, gpu-lbvh) and read back: the tree checked, the rays traced
#    over it in the browser (GPU and WebAssembly) against the CPU walk over the same tree,
#    bit for bit, with the build's time: prints `browser device build (gpu-ploc): built in
#    X ms ...; N hits, 0 differ from the CPU walks over the read-back tree`; then a user's
#    shader with a mistake, compiled after the traversal library on WebGPU: the page is
#    given an error naming its line (`browser shader error: mine.wgsl:6:...`); then, with
#    WebGPU's default limits, a 2.4M-triangle grid whose tree is bound in pages;
#  - the viewer (WebGPU on the system's Vulkan driver): its traced image against the
#    native render, pixel for pixel, and its window saved as web/dist/viewer-screenshot.png:
#    prints `browser viewer: N pixels, 0 differ`; then the same for an animated scene in two
#    levels, playing, for an alpha-tested one and for the path mode (its sums against the
#    path tracer's CPU twin); then that a bad flag and a broken file show their errors on
#    the page.
# Then the npm package (web/package.sh), in Node and in Chromium (see below).
# The library check also opens the example page (index.html) and checks the hits it prints,
# with the BVH built in WebAssembly and on the device. Exits non-zero on any difference or
# page error. Flags go to the library check (`--size WxH`, `--device-builders LIST|none`).
# Honours CARGO_TARGET_DIR.
set -euo pipefail
cd "$(dirname "$0")/.."
web/build.sh
cargo run --release -q -p bvhtrace-integration --example browser_parity -- web/dist "$@"
# A tree larger than one binding: 2.4M triangles whose 131 MB of nodes the page, asking
# for WebGPU's default limits (128 MiB bindings, 8 storage buffers), binds in pages.
if [ -f ../shared/scenes/glb/igea.glb ]; then
  cargo run --release -q -p bvhtrace-integration --example browser_parity -- web/dist \
    --scene builtin:grid:igea:3x3 --default-limits --device-builders none
else
  echo "SKIP: the tree in pages in the browser: no ../shared/scenes/glb/igea.glb"
fi
# The npm package (web/package.sh: packed, its TypeScript declarations compiled by tsc),
# as a user installs it: its API in Node; our hits against three-mesh-bvh's in Node, ray
# for ray; its WebAssembly walk in Chromium against the CPU walk here, bit for bit, and
# beside three-mesh-bvh on the same rays.
web/package.sh
pkg=web/dist/packed/package
node web/tests/api.mjs "$pkg" scenes/cornell.gltf
three_scenes=(scenes/cornell.gltf)
[ -f ../shared/scenes/glb/bunny_69k.glb ] && three_scenes+=(../shared/scenes/glb/bunny_69k.glb)
if [ -d web/node_modules/three-mesh-bvh ]; then
  node web/tests/three.mjs "$pkg" "${three_scenes[@]}"
  cargo run --release -q -p bvhtrace-integration --example browser_wasm -- "$pkg" --example web/dist
else
  echo "SKIP: three.js and three-mesh-bvh beside the package: web/node_modules has none (npm ci failed)"
  cargo run --release -q -p bvhtrace-integration --example browser_wasm -- "$pkg"
fi
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist
# Two levels and animation: the viewer plays scenes/animated.gltf from t = 1 s, each pose
# written into the upload in place; the image it shows against the native render at its time.
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist \
  --scene scenes/animated.gltf --time 1 --play --out web/dist/animated
# Alpha-tested geometry: the leaves and the fence of scenes/foliage.gltf cut by their masks
# on the page's WebGPU as the native render cuts them.
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist \
  --scene scenes/foliage.gltf --out web/dist/foliage
# The path mode: the alpha-tested scene path traced on the page's WebGPU (the wavefront
# kernel, its shadow rays cut by the masks), its sums read back once with the screenshot
# against the CPU twin's, bit for bit.
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist \
  --path --scene scenes/foliage.gltf --out web/dist/path
# Errors reach the page (and the test), never a blank canvas: a bad flag, a broken file.
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist \
  --flags "--shade sepia" --expect-error "invalid value 'sepia'"
cargo run --release -q -p bvhtrace-integration --example browser_viewer -- web/dist \
  --scene web/viewer.html --expect-error "scene.glb"
