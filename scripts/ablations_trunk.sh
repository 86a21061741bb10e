#!/usr/bin/env bash
# Ablations of the trunk recipe (scripts/train_trunk.sh): what the pretrained trunk,
# the evidence relative to the vehicle and the blink-frequency evidence each bring, on the
# own test split, the held-out style family, the independent generator and the hard
# negatives:
#
#   scripts/ablations_trunk.sh
#
#   full           the recipe's model (ImageNet trunk, relative evidence, lamp maps at 8x8
#                  stacked per trunk cell, a lit head with one hidden layer, blink evidence
#                  by period only)
#   no_relative    relative_evidence=false
#   blink_levels   blink_levels=true (the blinkers' P(lit) and peaks in the track vector)
#   no_periods     lit_periods=false (no blink-period evidence at all: frequency off)
#   coarse_lamps   lamp_detail=1 (one lamp-map cell per trunk cell)
#   linear_lit     lit_hidden=0 (a linear lit head)
#   random_trunk   trunk_init=random (the same frozen architecture, random weights)
#
# Every variant trains from scratch on the same pools, validation split and seed for
# STEPS steps (fewer than the shipped run's, the same for all), PARALLEL at a time with
# THREADS threads each; each is calibrated and scored like the shipped weights. The
# "today's encoder" row is the CNN model shipped before (CNN=FILE, by default read from
# git at CNN_COMMIT), scored the same way. Writes REPORT (Markdown).
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

export DATA=${DATA:-runs/default}   # the shipped run's splits (scripts/train_trunk.sh)
OUT=${OUT:-runs/ablations_trunk}
export STEPS=${STEPS:-600}
export VAL_EVERY=${VAL_EVERY:-200}
export THREADS=${THREADS:-1}
PARALLEL=${PARALLEL:-2}
CNN_COMMIT=${CNN_COMMIT:-6f587f0}
REPORT=${REPORT:-docs/results/ablations_trunk.md}
VARIANTS=(${VARIANTS:-full no_relative blink_levels coarse_lamps linear_lit random_trunk})
# The recipe's model (scripts/train_trunk.sh RECIPE_MODEL) and one change each.
BASE='"frequency_evidence": false, "lamp_detail": 2, "lit_hidden": 128'
declare -A MODELS=([full]="{$BASE, \"blink_levels\": false}"
                   [no_relative]="{$BASE, \"blink_levels\": false, \"relative_evidence\": false}"
                   [blink_levels]="{$BASE}"
                   [no_periods]="{$BASE, \"blink_levels\": false, \"lit_periods\": false}"
                   [coarse_lamps]='{"frequency_evidence": false, "lit_hidden": 128, "blink_levels": false}'
                   [linear_lit]='{"frequency_evidence": false, "lamp_detail": 2, "blink_levels": false}'
                   [random_trunk]="{$BASE, \"blink_levels\": false, \"trunk_init\": \"random\"}")

mkdir -p "$OUT"
run_variant() {
  local name=$1
  RUN="$OUT/$name" WEIGHTS="$OUT/$name/model.pt" MODEL="${MODELS[$name]}" EXPORT=0 \
    bash scripts/train_trunk.sh > "$OUT/$name.log" 2>&1
}
running=0
for name in "${VARIANTS[@]}"; do
  echo "== $name -> $OUT/$name (log $OUT/$name.log)"
  run_variant "$name" &
  running=$((running + 1))
  if (( running >= PARALLEL )); then wait -n; running=$((running - 1)); fi
done
wait
cnn=${CNN:-$OUT/cnn.pt}
[[ -f "$cnn" ]] || git show "$CNN_COMMIT:signal_light_node/weights/default.pt" > "$cnn"
[[ -f "$OUT/cnn/transfer/transfer.md" ]] || python scripts/transfer_report.py \
  --checkpoint "$cnn" --data "$DATA" --out "$OUT/cnn/transfer" --threads "$THREADS" > /dev/null
{
  echo "# Ablations of the trunk recipe ($STEPS steps each, the same data and seed)"
  echo
  for name in "${VARIANTS[@]}" cnn; do
    echo "## $name"
    echo
    cat "$OUT/$name/transfer/transfer.md"
    echo
  done
} > "$REPORT"
cat "$REPORT"
