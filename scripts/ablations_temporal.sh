#!/usr/bin/env bash
# Ablations of the temporal recipe (scripts/train_default.sh): what the temporal input and
# the randomisation each bring, on the own test split, the held-out style family and the
# independent generator's bags:
#
#   scripts/ablations_temporal.sh
#
#   full              the shipped settings (temporal input, camera response, shape warp)
#   no_temporal       MODEL= (the base architecture, fine-tuned the same way)
#   no_randomisation  TRAIN_ARGS=--freeze-norms (temporal input, no camera response or warp)
#
# Every variant fine-tunes the same base weights on the same pools for STEPS steps (the
# step count ends each run, not the clock, so sharing the cores changes the time, not the
# result) with THREADS threads each, side by side; each is then scored with
# scripts/transfer_report.py. Writes REPORT (Markdown) with one block per variant.
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

export DATA=${DATA:-runs/default}            # the shipped run's splits and base weights
OUT=${OUT:-runs/ablations_temporal}
export STEPS=${STEPS:-300}
export MINUTES=${MINUTES:-600}
export VAL_EVERY=${VAL_EVERY:-150}
export THREADS=${THREADS:-1}
export EVAL=0
export BASE=${BASE:-$DATA/base.pt}
REPORT=${REPORT:-docs/results/ablations_temporal.md}
VARIANTS=(${VARIANTS:-full no_temporal no_randomisation})

declare -A MODELS=([full]="temporal_input=true" [no_temporal]="" [no_randomisation]="temporal_input=true")
declare -A AUGMENT=([full]="--camera-response --shape-warp --freeze-norms --grown-init-scale 0.25" [no_temporal]="--camera-response --shape-warp --freeze-norms"
                    [no_randomisation]="--freeze-norms --grown-init-scale 0.25")

mkdir -p "$OUT"
pids=()
for name in "${VARIANTS[@]}"; do
  echo "== $name -> $OUT/$name (log $OUT/$name.log)"
  RUN="$OUT/$name" WEIGHTS="$OUT/$name/model.pt" MODEL="${MODELS[$name]}" \
    TRAIN_ARGS="${AUGMENT[$name]}" bash scripts/train_default.sh > "$OUT/$name.log" 2>&1 &
  pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done
{
  echo "# Ablations of the temporal recipe ($STEPS steps each from the same base weights)"
  echo
  for name in "${VARIANTS[@]}"; do
    python scripts/transfer_report.py --checkpoint "$OUT/$name/model.pt" --data "$DATA" \
      --out "$OUT/$name/transfer" --threads "$THREADS" > /dev/null
    echo "## $name"
    echo
    cat "$OUT/$name/transfer/transfer.md"
    echo
  done
} > "$REPORT"
cat "$REPORT"
