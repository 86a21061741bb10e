#!/usr/bin/env bash
# Ablations of the research on the base recipe (attention vs none; multi-task vs intent-only):
#
#   scripts/ablations.sh
#
# Trains three variants with the shipped recipe (scripts/train_base.sh) on the same
# pool, validation and test splits, with the same seed and the same number of steps
# (shorter than the shipped run), evaluates each with `signal-light evaluate` on the same
# test split, and writes the comparison to docs/results/ablations.md (and .json).
#
#   full          the shipped architecture and loss
#   no_attention  --model use_attention=false (the crop goes to the backbone unmasked)
#   intent_only   --task-weights intent=1,brake=0,left=0,right=0,view=0
#
# The variants run side by side with THREADS threads each (fixed steps, so sharing the
# cores changes the time, not the result). 31 minutes on this 2-core CPU once the
# splits exist in DATA (train_default.sh renders them there first if they do not).
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

export DATA=${DATA:-runs/default}           # shared splits (those of the shipped run)
OUT=${OUT:-runs/ablations}
export FRAME_STEPS=${FRAME_STEPS:-2500}
export LANE_STEPS=${LANE_STEPS:-300}
export FRAME_MINUTES=${FRAME_MINUTES:-600}  # the step counts end each stage, not the clock
export LANE_MINUTES=${LANE_MINUTES:-600}
export VAL_EVERY=${VAL_EVERY:-500}
export THREADS=${THREADS:-1}
REPORT=${REPORT:-docs/results/ablations.md}
VARIANTS=(full no_attention intent_only)

declare -A ARGS=(
  [full]=""
  [no_attention]="--model use_attention=false"
  [intent_only]="--task-weights intent=1,brake=0,left=0,right=0,view=0"
)

mkdir -p "$OUT"
# Render the shared splits once, before the variants start reading them.
if [[ ! -f "$DATA/test_split/manifest.json" ]]; then
  echo "== rendering the shared splits in $DATA"
  DATA_ONLY=1 bash scripts/train_base.sh
fi

start=$(date +%s)
pids=()
for name in "${VARIANTS[@]}"; do
  echo "== $name: ${ARGS[$name]:-(shipped settings)} -> $OUT/$name (log $OUT/$name.log)"
  RUN="$OUT/$name" WEIGHTS="$OUT/$name/model.pt" TRAIN_ARGS="${ARGS[$name]}" \
    bash scripts/train_base.sh > "$OUT/$name.log" 2>&1 &
  pids+=($!)
done
failed=0
for i in "${!pids[@]}"; do
  if ! wait "${pids[$i]}"; then
    echo "variant ${VARIANTS[$i]} failed; see $OUT/${VARIANTS[$i]}.log" >&2
    failed=1
  fi
done
[[ $failed == 0 ]] || exit 1
echo "== variants done in $(( ($(date +%s) - start) / 60 )) minutes"

python -m signal_light_node.training.ablation_report --out "$REPORT" \
  --command "scripts/ablations.sh (FRAME_STEPS=$FRAME_STEPS LANE_STEPS=$LANE_STEPS)" \
  $(for name in "${VARIANTS[@]}"; do echo "$name=$OUT/$name"; done)
cat "$REPORT"
