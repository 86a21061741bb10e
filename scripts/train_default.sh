#!/usr/bin/env bash
# Produce the shipped weights signal_light_node/weights/default.pt -- the one documented
# command (about 35 minutes on a 2-core CPU with the defaults below: 20 of rendering, 5 of
# training, 10 of evaluation). The shipped model is the small CNN encoder with temporal
# input; scripts/train_trunk.sh trains the pretrained-trunk model (not shipped yet, see
# docs/model.md):
#
#   scripts/train_default.sh                   # CPU
#   DEVICE=cuda THREADS=16 scripts/train_default.sh   # a GPU machine (see README)
#
# What it does:
#   1. renders the data in parallel worker processes (one per seed): POOL_SEEDS pools of
#      POOL_TRACKS whole tracks (style families 0 and 1 only), a validation split
#      (windows), the own test split (whole tracks, families 0 and 1) and the held-out
#      family test split (whole tracks, style family 2: lamp colours and camera tone
#      curves never rendered for training);
#   2. takes the base weights: by default the per-frame encoder and lanes trained by
#      scripts/train_base.sh and shipped until 2026-11-22 (read from git at BASE_COMMIT,
#      so nothing is downloaded); BASE=FILE uses another checkpoint, BASE=train runs
#      scripts/train_base.sh first (about 83 minutes more);
#   3. fine-tunes it with temporal evidence (--model temporal_input=true: the crop's
#      change against the track's previous crop and running mean as 6 more input
#      channels, zero-initialised so training starts from the base model's outputs) as
#      stateful lanes (--mode lanes: LANES tracks side by side, SEQ_LEN frames per step,
#      the state carried across steps as in the node), with a random camera response per
#      track (--camera-response) and a cosine learning-rate decay over the last ANNEAL
#      share of MINUTES; resumable (an interrupted run continues from last.pt);
#   4. copies the best checkpoint (validation score with the state carried) to WEIGHTS;
#   5. scores it on the own and held-out family test splits and the independent
#      generator's bags with scripts/transfer_report.py (RUN/transfer).
#
# Every setting can be overridden from the environment; a 3-minute smoke run:
#   RUN=runs/smoke POOL_SEEDS=31 POOL_TRACKS=24 VAL_SEQUENCES=16 TEST_TRACKS=12 \
#     TEST_FRAMES=40 MINUTES=1 WEIGHTS=runs/smoke/default.pt scripts/train_default.sh
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

RUN=${RUN:-runs/default}
DATA=${DATA:-$RUN}
WEIGHTS=${WEIGHTS:-signal_light_node/weights/default.pt}
BASE=${BASE:-git}                    # git | train | a checkpoint file
BASE_COMMIT=${BASE_COMMIT:-b0d71f1}  # the commit whose shipped weights are the base
SEED=${SEED:-1}
POOL_SEEDS=${POOL_SEEDS:-"31 32 33"}
# The other data settings (POOL_TRACKS, VAL_*, TEST_*, FAMILY_SEED, CAL_*): scripts/render_data.sh.
MINUTES=${MINUTES:-45}               # a cap; STEPS ends the run first
STEPS=${STEPS:-150}                 # the best validation came at step 150 (see docs/model.md)
LANES=${LANES:-32}
SEQ_LEN=${SEQ_LEN:-12}
LR=${LR:-2e-4}
VAL_EVERY=${VAL_EVERY:-150}
ANNEAL=${ANNEAL:-0}
MODEL=${MODEL-temporal_input=true}  # --model changes on top of the base architecture
TRAIN_ARGS=${TRAIN_ARGS---camera-response --shape-warp --freeze-norms --grown-init-scale 0.25}
PRECISION=${PRECISION:-auto}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-2}
EVAL=${EVAL:-1}                      # 0: stop after copying the weights (ablations evaluate)

mkdir -p "$RUN" "$DATA"
start=$(date +%s)
echo "== 1/5 data in $DATA: pools (seeds $POOL_SEEDS), validation, test, held-out family test"
pools=()
for seed in $POOL_SEEDS; do pools+=(--pool "$DATA/pool_$seed"); done
DATA=$DATA POOL_SEEDS=$POOL_SEEDS CAL_TRACKS=0 bash scripts/render_data.sh
if [[ -n "${DATA_ONLY:-}" ]]; then
  echo "== DATA_ONLY set: splits ready in $DATA"
  exit 0
fi

echo "== 2/5 base weights ($BASE)"
base=$BASE
if [[ "$BASE" == git ]]; then
  base="$RUN/base.pt"
  [[ -f "$base" ]] || git show "$BASE_COMMIT:signal_light_node/weights/default.pt" > "$base"
elif [[ "$BASE" == train ]]; then
  base="$RUN/base/default.pt"
  [[ -f "$base" ]] || RUN="$RUN/base" WEIGHTS="$base" bash scripts/train_base.sh
fi

echo "== 3/5 temporal fine-tune: $MINUTES minutes, $LANES lanes x $SEQ_LEN frames"
resume=()
if [[ -f "$RUN/temporal/summary.json" ]]; then
  echo "$RUN/temporal/summary.json exists: finished before; skipping"
else
  if [[ -f "$RUN/temporal/last.pt" && -f "$RUN/temporal/last.state.pt" ]]; then
    resume=(--resume)
  fi
  # shellcheck disable=SC2086  # TRAIN_ARGS is split into words on purpose
  signal-light train --out "$RUN/temporal" --mode lanes --init-from "$base" --model "$MODEL" \
    --max-minutes "$MINUTES" --steps "$STEPS" --batch "$LANES" --seq-len "$SEQ_LEN" \
    --lr "$LR" --val-every "$VAL_EVERY" --anneal-fraction "$ANNEAL" --seed "$SEED" \
    --val-split "$DATA/val_split" --threads "$THREADS" --workers 0 --device "$DEVICE" \
    --precision "$PRECISION" "${pools[@]}" $TRAIN_ARGS "${resume[@]}"
fi

echo "== 4/5 best checkpoint -> $WEIGHTS"
mkdir -p "$(dirname "$WEIGHTS")"
cp "$RUN/temporal/best.pt" "$WEIGHTS"

if [[ "$EVAL" != 1 ]]; then
  echo "== EVAL=0: not evaluated"
  exit 0
fi
echo "== 5/5 evaluation: own test split, held-out style family, independent generator"
python scripts/transfer_report.py --checkpoint "$WEIGHTS" --data "$DATA" --out "$RUN/transfer" \
  --threads "$THREADS"
echo "== done in $(( ($(date +%s) - start) / 60 )) minutes; reports: $RUN/transfer/transfer.md" \
  "and $RUN/transfer/{own,family,independent}/metrics.md"
