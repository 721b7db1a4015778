#!/usr/bin/env bash
# The CPU tracer against Embree 3 and 4.4 at 1, 2, 4, 8 and 16 threads, prepared for the
# device machine's 16 cores (docs/cpu-tracer.md, "Diffuse-bounce rays and a thread
# sweep"): `bench-trace --cpu-only --threads 1,2,4,8,16` on bunny_69k and igea (primary,
# shadow and diffuse-bounce rays, 0 differing answers expected), then a grid placed in two
# levels. About 4 minutes on 16 cores; the tables and the sweep land in OUT/sweep.txt.
#
#   docs/device-cpu-sweep.sh [BVHTRACE_BINARY] [SCENE_DIR] [EMBREE3_TRACE] [EMBREE4_TRACE] [OUT]
#
# Build here and carry: the release binary (`cargo build --release -p bvhtrace-cli`), the
# scenes (`../shared/scenes/glb`), `embree_trace` built against Embree 3 with its
# libraries beside it (`libembree3.so.3` and `libtbb.so.12` copied next to it: the
# script puts its folder on LD_LIBRARY_PATH), and the Embree 4.4 build, whose runtime and
# TBB come from the embreex wheel (`embreex.libs/`, found through its rpath: carry that
# folder at the same path, or relink). A helper left out (an empty argument or a missing
# file) drops its columns.
set -euo pipefail
B=${1:-target/release/bvhtrace}
S=${2:-../shared/scenes/glb}
E3=${3:-/tmp/embree_trace}
E4=${4:-/tmp/embree4_trace}
OUT=${5:-${OUT:-/tmp/cpu-sweep}}
mkdir -p "$OUT"
helpers=()
if [ -n "$E3" ] && [ -x "$E3" ]; then
  export LD_LIBRARY_PATH="$(cd "$(dirname "$E3")" && pwd)${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  helpers+=(--embree "$E3")
fi
[ -n "$E4" ] && [ -x "$E4" ] && helpers+=(--embree4 "$E4")
{
  lscpu | grep -E 'Model name|^CPU\(s\)|Thread|L2|L3' || true
  "$B" bench-trace --cpu-only --traversals full-stack --runs 5 --threads 1,2,4,8,16 \
    "${helpers[@]}" "$S/bunny_69k.glb" "$S/igea.glb"
  # The grid finds its mesh in a `shared/scenes/glb` folder above the working folder.
  "$B" bench-trace --cpu-only --traversals full-stack --runs 5 --threads 16 \
    "${helpers[@]}" builtin:grid:bunny_69k:3x3 || echo "grid skipped: no shared/scenes above $PWD"
} 2>&1 | tee "$OUT/sweep.txt"
