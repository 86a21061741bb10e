#!/usr/bin/env bash
# Which trunk blocks should learn? The per-frame stage of the trunk recipe
# (signal_light_node/training/trunk_finetune.py) in several arms side by side, the same pools,
# validation splits, seed and budget; each arm's best.pt (chosen on the family calibration
# split) goes to OUT/ARM/best.pt and its validation history to OUT/ARM/history.jsonl.
#
#   DATA=runs/v15 OUT=runs/frames DEVICE=cuda WORKERS=3 MINUTES=4 bash scripts/ablations_frames.sh
#
# ARMS lists NAME:TRAIN_FROM pairs (11: the trunk frozen, only the per-frame head learns;
# 8: the last stage; 5: both stride-16 stages; -1: every block and the stem). The data are
# the trunk recipe's (scripts/render_data.sh with CAL_TRACKS=120, rendered when missing).
# docs/model.md, "The trunk fine-tuned frame by frame", has the figures of 2026-11-26
# (H200, 64 tracks x 8 frames per step, 4 minutes per arm, four arms at once).
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi
DATA=${DATA:-runs/default}
OUT=${OUT:-runs/ablations_frames}
ARMS=${ARMS:-"F:11 L:8 M:5 A:-1"}
POOL_SEEDS=${POOL_SEEDS:-"31 32 33"}
STEPS=${STEPS:-8000}
MINUTES=${MINUTES:-0}
TRACKS=${TRACKS:-64}
WORKERS=${WORKERS:-0}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-1}
SEED=${SEED:-1}

DATA=$DATA POOL_SEEDS=$POOL_SEEDS CAL_TRACKS=${CAL_TRACKS:-120} bash scripts/render_data.sh
pools=()
for seed in $POOL_SEEDS; do pools+=(--pool "$DATA/pool_$seed"); done
mkdir -p "$OUT"
for arm in $ARMS; do
  name=${arm%%:*}
  mkdir -p "$OUT/$name"
  python -m signal_light_node.training.trunk_finetune --out "$OUT/$name" "${pools[@]}" \
    --val "$DATA/val_split" --val "$DATA/family_cal_split" --train-from "${arm##*:}" \
    --steps "$STEPS" --minutes "$MINUTES" --tracks "$TRACKS" --per-track 8 \
    --workers "$WORKERS" --threads "$THREADS" --device "$DEVICE" --seed "$SEED" \
    --val-every 1000 > "$OUT/$name/log" 2>&1 &
done
wait
for arm in $ARMS; do
  echo "== ${arm%%:*} (train from ${arm##*:}): $(cat "$OUT/${arm%%:*}/summary.json" | tr -d '\n ')"
done
