#!/usr/bin/env bash
# Produce the shipped weights signal_light_node/weights/default.pt -- the one documented
# command (about 85 minutes on a 2-core CPU with the defaults below):
#
#   scripts/train_default.sh
#
# Steps:
#   1. materialise a validation split (windows) and a held-out test split (whole tracks)
#      from stream seeds that training never uses;
#   2. train from scratch on the synthetic stream for TRAIN_MINUTES, validating every
#      VAL_EVERY steps and keeping the best checkpoint (intent macro-F1 + brake accuracy);
#   3. copy the best checkpoint to signal_light_node/weights/default.pt;
#   4. evaluate it frame by frame on the test split (metrics.json / metrics.md / PNG in
#      RUN/test_eval) and print the Markdown table.
#
# Every setting can be overridden from the environment, e.g. a 5-minute smoke run:
#   RUN=runs/smoke TRAIN_MINUTES=3 VAL_SEQUENCES=16 TEST_TRACKS=12 TEST_FRAMES=40 \
#     WEIGHTS=runs/smoke/default.pt scripts/train_default.sh
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

RUN=${RUN:-runs/default}
WEIGHTS=${WEIGHTS:-signal_light_node/weights/default.pt}
SEED=${SEED:-1}                      # training stream, model init
VAL_SEED=${VAL_SEED:-700001}         # validation split
TEST_SEED=${TEST_SEED:-900001}       # test split: never trained or validated on
TRAIN_MINUTES=${TRAIN_MINUTES:-75}
MAX_STEPS=${MAX_STEPS:-100000}       # the time budget is what normally stops training
BATCH=${BATCH:-8}
SEQ_LEN=${SEQ_LEN:-24}
LR=${LR:-1e-3}
VAL_EVERY=${VAL_EVERY:-250}
VAL_SEQUENCES=${VAL_SEQUENCES:-128}
VAL_LEN=${VAL_LEN:-48}
TEST_TRACKS=${TEST_TRACKS:-240}
TEST_FRAMES=${TEST_FRAMES:-150}
THREADS=${THREADS:-1}                # torch threads of the trainer; the other core renders
WORKERS=${WORKERS:-1}

mkdir -p "$RUN"
start=$(date +%s)
echo "== 1/4 splits: validation (seed $VAL_SEED) and test (seed $TEST_SEED) in $RUN"
python - "$RUN" "$VAL_SEED" "$VAL_SEQUENCES" "$VAL_LEN" "$TEST_SEED" "$TEST_TRACKS" "$TEST_FRAMES" <<'EOF'
import sys
from pathlib import Path

from signal_light_node.data.split import write_split
from signal_light_node.model import ModelConfig

run, val_seed, val_n, val_len, test_seed, test_n, test_len = sys.argv[1:]
crop = ModelConfig().crop_config()
for name, seed, n, length, full in (("val_split", val_seed, val_n, val_len, False),
                                    ("test_split", test_seed, test_n, test_len, True)):
    out = Path(run) / name
    if (out / "manifest.json").is_file():
        print(f"{out} exists; reusing it")
        continue
    write_split(out, seed=int(seed), n_sequences=int(n), seq_len=int(length), crop=crop,
                full_tracks=full)
EOF

echo "== 2/4 training for $TRAIN_MINUTES minutes (batch $BATCH x $SEQ_LEN frames)"
if [[ -f "$RUN/train/summary.json" ]]; then
  echo "$RUN/train/summary.json exists: training finished before; skipping"
else
  resume=()
  if [[ -f "$RUN/train/last.pt" && -f "$RUN/train/last.state.pt" ]]; then
    resume=(--resume)   # an interrupted run continues (with a fresh time budget)
  fi
  signal-light train --out "$RUN/train" --seed "$SEED" --max-minutes "$TRAIN_MINUTES" \
    --steps "$MAX_STEPS" --batch "$BATCH" --seq-len "$SEQ_LEN" --lr "$LR" \
    --val-split "$RUN/val_split" --val-every "$VAL_EVERY" --threads "$THREADS" \
    --workers "$WORKERS" "${resume[@]}"
fi

echo "== 3/4 best checkpoint -> $WEIGHTS"
mkdir -p "$(dirname "$WEIGHTS")"
cp "$RUN/train/best.pt" "$WEIGHTS"

echo "== 4/4 evaluation on the held-out test split"
signal-light evaluate --checkpoint "$WEIGHTS" --split "$RUN/test_split" \
  --out "$RUN/test_eval" --threads 2

echo "== done in $(( ($(date +%s) - start) / 60 )) minutes; report: $RUN/test_eval/metrics.md"
