#!/usr/bin/env bash
# Issue 51's device checks, prepared for a device machine: the wall against the dispatch
# with 1 and 2 submissions in flight, the walks on shadow and diffuse rays beside the cost
# model's prediction for them, and the device builders at 6.7M triangles. About five
# minutes on an H100 or H200; every output lands in OUT.
#
#   docs/device-wall.sh [TARGET_DIR] [SCENE_DIR] [OUT]
#
# Build here first (`cargo build --release -p bvhtrace-cli -p bvhtrace-gpu --examples`) and
# carry target/release's `bvhtrace`, `examples/gpu_bench` and `examples/gpu_build` with the
# scenes (`../shared/scenes`).
set -euo pipefail
T=${1:-target/release}
S=${2:-../shared/scenes}
OUT=${3:-${OUT:-/tmp/device-wall}}
mkdir -p "$OUT"
(nvidia-smi -L || true) > "$OUT/gpu.txt" 2>&1
# Wall against dispatch, 1M primary rays, alternated.
for round in 1 2; do
  for n in 1 2; do
    "$T/examples/gpu_bench" "$S/glb/bunny_69k.glb" "$S/glb/igea.glb" --size 1024x1024 \
      --storage buffers --traversals full-stack,stackless,wide --runs 5 --in-flight "$n" \
      > "$OUT/bench-in-flight-$n-round-$round.txt" 2>&1
  done
done
# The walks on the ray kinds the cost model predicts for (work/warp against the full
# stack: wide 0.80-0.87x on shadow and diffuse rays), and the model beside them.
for kind in primary shadow diffuse; do
  "$T/bvhtrace" bench-trace "$S/glb/bunny_69k.glb" "$S/glb/igea.glb" --runs 5 \
    --traversals full-stack,stackless,wide --any-hit --rays "$kind" \
    > "$OUT/bench-trace-$kind.txt" 2>&1
done
"$T/bvhtrace" cost --walks full-stack,stackless,wide --json "$OUT/cost.json" \
  > "$OUT/cost.txt" 2>&1
# The device builders: one wait per build, one copy back; against the 16-thread CPU build.
"$T/examples/gpu_build" builtin:grid:igea:5x5 --runs 3 > "$OUT/build-5x5.txt" 2>&1 || echo "the 5x5 grid did not build: see $OUT/build-5x5.txt"
"$T/examples/gpu_build" "$S/glb/bunny_69k.glb" "$S/glb/igea.glb" --runs 5 \
  > "$OUT/build.txt" 2>&1
grep -h -E "^(full-stack|stackless|wide) " "$OUT"/bench-in-flight-*.txt || true
grep -h -E "gpu-ploc|gpu-lbvh|cpu-sah" "$OUT"/build*.txt || true
