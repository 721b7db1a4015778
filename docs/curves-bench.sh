#!/usr/bin/env bash
# Curves against Embree 3 on the same rays, and against the same strands as triangles:
# for each kind of `builtin:hair` (and `hair:tubes`), our CPU layout and our wgpu walk
# (`render --json`'s primary rays per second, the trace alone), and Embree 3's robust
# mode on the rays `bvhtrace dump` writes (its trace alone, 2 threads). Medians of RUNS
# alternated rounds; one line per row.
#
#   docs/curves-bench.sh [TARGET_DIR] [RUNS] [STRANDS]
set -euo pipefail
T=${1:-target/release}
RUNS=${2:-3}
N=${3:-10000}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
cc -O2 crates/cli/embree/embree_trace.c -lembree3 -lpthread -lm -o "$W/embree_trace"
median() { sort -g | awk '{a[NR]=$1} END {print a[int((NR + 1) / 2)]}'; }
field() { python3 -c "import json,sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])" "$@"; }
printf "%-26s %10s %10s %9s %9s %9s %9s %11s\n" scene hits emb-hits cpu wgpu embree3 cpu/emb bytes
for kind in round-linear flat-linear round-bezier round-bspline tubes; do
  scene="builtin:hair:$kind:$N"
  "$T/bvhtrace" dump "$scene" -o "$W/d.bin" 2>/dev/null
  key=primary_mrays_per_s
  [ "$kind" = tubes ] && key=mrays_per_s
  : > "$W/cpu"; : > "$W/gpu"; : > "$W/emb"
  for r in $(seq "$RUNS"); do
    "$T/bvhtrace" render "$scene" --backend cpu -o "$W/c.png" --json "$W/c.json" 2>/dev/null
    field "$W/c.json" "$key" >> "$W/cpu"
    "$T/bvhtrace" render "$scene" --backend gpu -o "$W/g.png" --json "$W/g.json" 2>/dev/null
    field "$W/g.json" "$key" >> "$W/gpu"
    "$W/embree_trace" "$W/d.bin" 2 1 > "$W/e.json"
    field "$W/e.json" mrays_per_s >> "$W/emb"
  done
  hits=$(field "$W/c.json" hits)
  bytes=$(python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(d.get('bvh_bytes') or d.get('mesh_bytes'))" "$W/c.json")
  c=$(median < "$W/cpu"); g=$(median < "$W/gpu"); e=$(median < "$W/emb")
  ehits=$(field "$W/e.json" hits)
  printf '%-26s %10s %10s %9.2f %9.2f %9.2f %9.2f %11s\n' "$scene" "$hits" "$ehits" "$c" "$g" "$e" \
    "$(python3 -c "print($c / $e)")" "$bytes"
done
