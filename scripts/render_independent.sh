#!/usr/bin/env bash
# Render the larger independent evaluation set (the second generator, signal_light_node.evalgen,
# never trained on) into OUT, once: DAY_SEEDS by day and NIGHT_SEEDS by night, 100 frames of
# 640x360 each, as the committed independent bags are made. A bag that exists is reused.
# About 20 s per bag on one core. scripts/transfer_report.py --independent-renders OUT/*
# scores them beside the two committed bags.
#
#   scripts/render_independent.sh runs/indep
set -euo pipefail

cd "$(dirname "$0")/.."
OUT=${1:?usage: render_independent.sh OUT}
DAY_SEEDS=${DAY_SEEDS:-"101 102 103 104 105 106"}
NIGHT_SEEDS=${NIGHT_SEEDS:-"201 202 203 204 205 206"}
mkdir -p "$OUT"
for lighting in day night; do
  seeds=$DAY_SEEDS
  [[ $lighting == night ]] && seeds=$NIGHT_SEEDS
  for seed in $seeds; do
    bag="$OUT/${lighting}_$seed"
    [[ -d "$bag" ]] && continue
    python -m signal_light_node.evalgen -o "$bag" --seed "$seed" --lighting "$lighting" \
      --width 640 --height 360 --frames 100 --jpeg-quality 80
  done
done
