#!/usr/bin/env bash
# The path tracer's frame against the walk's own dispatch rate on one GPU, prepared for a
# device machine (docs/benchmarks.md, "The path tracer"): 1920x1080 frames of 1 sample
# per pixel (the CLI waits for each), each kernel, 8 bounces and 1, beside the same walk's
# primary rays as one batch (`--shade normal`, its dispatch timestamped). A few minutes on
# a GPU; every figure lands as JSON in OUT, and a summary is printed.
#
#   docs/device-path-rate.sh [BVHTRACE_BINARY] [SCENE_DIR] [OUT]
#
# Build the binary here (`cargo build --release -p bvhtrace-cli`) and carry it with the
# scenes (`../shared/scenes/glb`).
set -euo pipefail
B=${1:-target/release/bvhtrace}
S=${2:-../shared/scenes/glb}
OUT=${3:-${OUT:-/tmp/path-rate}}
mkdir -p "$OUT"
(nvidia-smi -L || true) > "$OUT/gpu.txt" 2>&1
for scene in bunny_69k igea; do
  for walk in stackless full-stack; do
    "$B" render "$S/$scene.glb" --shade normal --size 1920x1080 --runs 5 --traversal "$walk" \
      --json "$OUT/walk-$scene-$walk.json" --output "$OUT/walk-$scene-$walk.png" 2>/dev/null
    for kernel in wavefront megakernel; do
      for depth in 8 1; do
        name="path-$scene-$walk-$kernel-$depth"
        "$B" render "$S/$scene.glb" --shade path --spp 16 --size 1920x1080 --traversal "$walk" \
          --kernel "$kernel" --max-depth "$depth" --sun 0.4,1,0.3 \
          --json "$OUT/$name.json" --output "$OUT/$name.png" 2>/dev/null
      done
    done
  done
done
python3 - "$OUT" <<'PY'
import glob, json, os, sys
out = sys.argv[1]
for f in sorted(glob.glob(os.path.join(out, "*.json"))):
    j = json.load(open(f))
    name = os.path.basename(f)[:-5]
    if name.startswith("walk"):
        t = j.get("gpu_ms")
        print(f"{name}: dispatch {2073600 / t / 1e3:.1f} Mrays/s ({t:.2f} ms)" if t else f"{name}: no timestamps")
    else:
        print(f"{name}: {j['mrays_per_s']:.1f} Mrays/s of frames, {j['spp'] / j['seconds']:.1f} frames/s")
PY
