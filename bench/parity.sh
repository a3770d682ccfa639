#!/usr/bin/env bash
# One source tree's numbers on fixed maps: eval (plain and --align), export (FP32 + INT8 + keyframes), edge replay
# (FP32, INT8, INT8 --align) and a fixed-iteration Stage 2 with its render, on the built-in room and herzjesu25.
# The maps are made once (by the first tree run) and reused, so two trees' differences are the code's:
#   bench/parity.sh SRC DESKTOP_MODULE EDGE_MODULE OUT TAG     (e.g. . acesplat.apps.cli acesplat.apps.edge_cli)
#   python bench/parity_compare.py OUT TAG_A TAG_B
set -euo pipefail
SRC=$(cd "$1" && pwd); ENT=$2; EDGE=$3; OUT=$4; TAG=$5
HERZ=${HERZ:-$(cd ../shared/data/herzjesu25 && pwd)}  # run from the repository root
mkdir -p "$OUT"
run() { local mod=$1; shift; PYTHONPATH=$SRC python -P -c "import sys; from $mod import main; sys.argv[0]='x'; main()" "$@"; }
[ -d "$OUT/room" ] || run "$ENT" synth "$OUT/room"
for s in room herz; do
  scene=$OUT/room; [ $s = herz ] && scene=$HERZ
  [ -f "$OUT/$s.map.pt" ] || run "$ENT" map "$scene" -o "$OUT/$s.map.pt" --json "$OUT/$s.map.json"
  d=$OUT/$TAG/$s; mkdir -p "$d"
  run "$ENT" eval "$OUT/$s.map.pt" "$scene" --json "$d/eval.json"
  run "$ENT" eval "$OUT/$s.map.pt" "$scene" --align --json "$d/eval_align.json"
  rm -rf "$d/bundle"; run "$ENT" export "$OUT/$s.map.pt" -o "$d/bundle" --int8 --keyframes --scene "$scene"
  run "$EDGE" replay "$d/bundle" "$scene" --json "$d/replay_fp32.json"
  run "$EDGE" replay "$d/bundle" "$scene" --int8 --json "$d/replay_int8.json"
  run "$EDGE" replay "$d/bundle" "$scene" --int8 --align --json "$d/replay_int8_align.json"
  rm -rf "$d/splat"; run "$ENT" splat "$scene" --map "$OUT/$s.map.pt" -o "$d/splat" --iterations 300 --json "$d/splat.json"
  run "$ENT" render "$d/splat" "$scene" --json "$d/render.json"
done
