#!/usr/bin/env bash
# The base recipe (until 2026-11-22 the shipped one): per-frame stage + lanes, from nothing.
# scripts/train_default.sh starts from its weights (about 83 minutes on a 2-core CPU):
#
#   WEIGHTS=runs/base/default.pt scripts/train_base.sh
#
# Steps:
#   1. materialise the training pool (POOL_TRACKS whole tracks per seed of POOL_SEEDS,
#      rendered in parallel), a pool of short tracks for stage 1 only (FRAME_POOL_TRACKS
#      tracks of at most FRAME_POOL_FRAMES frames per seed of FRAME_POOL_SEEDS), a
#      validation split (windows) and a held-out test split (whole tracks) from seeds
#      that training never uses;
#   2. stage 1, per-frame pre-training (--mode frames): FRAME_BATCH single frames from
#      anywhere in both pools per step, so every step sees many different vehicles (the
#      short tracks give about four times as many vehicles per rendered frame and per
#      byte of memory: the encoder overfits the vehicles it has seen); with
#      FRAME_TARGETS=lit (default) the heads learn what each frame shows (a blinker in
#      the dark half of its blink counts as off), not the logical states, whose dark
#      halves are noise to a model that sees one frame;
#      stage 2, stateful lanes (--mode lanes) from the stage-1 weights: LANES tracks
#      played side by side, SEQ_LEN frames per step, each lane's ConvLSTM state carried
#      from step to step as in the node (this is where blinks are learnt); with
#      LANE_FREEZE=1 (default) the attention and backbone keep their stage-1 weights
#      (--freeze-encoder): steps cost about a quarter less, and the per-frame features,
#      which overfit the pool's vehicles when trained on, stay as stage 1 left them;
#      both stages end with a cosine decay of the learning rate over the last ANNEAL share
#      of their minutes (--anneal-fraction): they stop by their budget while the loss still
#      falls, and a full learning rate would leave the weights at a noisy point; with
#      PRECISION=auto (default) their forward passes run in bfloat16 where the CPU has
#      AVX512-BF16 (about 1.2x the steps in the same minutes), else in float32;
#   3. stage 2's best checkpoint (validation score, tracks stepped with their state as in
#      the node) is copied to signal_light_node/weights/default.pt;
#   4. it is evaluated frame by frame on the test split (metrics.json / metrics.md / PNG
#      in RUN/test_eval) and the Markdown table is printed.
#
# Why two stages: windows of consecutive frames from a few vehicles are nearly the same
# picture, so on 2 cores sequence-only training from scratch barely moved in an hour;
# single frames from many vehicles teach the attention and backbone quickly, and the
# lanes then only have to learn time.
#
# Every setting can be overridden from the environment, e.g. a 3-minute smoke run:
#   RUN=runs/smoke POOL_TRACKS=16 FRAME_POOL_TRACKS=32 FRAME_MINUTES=1 LANE_MINUTES=1 \
#     VAL_SEQUENCES=16 TEST_TRACKS=12 TEST_FRAMES=40 WEIGHTS=runs/smoke/default.pt \
#     scripts/train_base.sh
# DATA keeps the rendered splits apart from RUN (the checkpoints), TRAIN_ARGS adds options
# to both stages, FRAME_ARGS to stage 1 only, LIT_MAPS=1 renders the pools with lit maps
# (where each vehicle's lamps are lit: FRAME_ARGS="--model lit_map_head=true
# --lit-map-weight 1" trains on them, docs/model.md) and FRAME_STEPS / LANE_STEPS cap
# them by steps: scripts/ablations.sh uses
# these to train variants on the same data with the same number of steps; OBLIQUE=SHARE
# renders that share of the pools' front and rear views turned (synth.traffic, default 0;
# the validation and test splits never); DATA_ONLY=1 stops after rendering the splits.
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

RUN=${RUN:-runs/default}
DATA=${DATA:-$RUN}                   # where the pool, validation and test splits live
TRAIN_ARGS=${TRAIN_ARGS:-}           # extra `signal-light train` options for both stages
WEIGHTS=${WEIGHTS:-$RUN/default.pt}
SEED=${SEED:-1}                      # model init and sampling
POOL_SEEDS=${POOL_SEEDS:-"11 12 13 14"}  # training pool: one split per seed
POOL_TRACKS=${POOL_TRACKS:-800}      # whole tracks per pool seed
POOL_FRAMES=${POOL_FRAMES:-150}      # frames per rendered scene
FRAME_POOL_SEEDS=${FRAME_POOL_SEEDS-"21 22 23 24"}  # short tracks, stage 1 only ("" = none)
FRAME_POOL_TRACKS=${FRAME_POOL_TRACKS:-2400}  # tracks per seed
FRAME_POOL_FRAMES=${FRAME_POOL_FRAMES:-40}    # frames per rendered scene
VAL_SEED=${VAL_SEED:-700001}         # validation split
TEST_SEED=${TEST_SEED:-900001}       # test split: never trained or validated on
FRAME_MINUTES=${FRAME_MINUTES:-54}   # stage 1
FRAME_STEPS=${FRAME_STEPS:-1000000}  # (the time budget ends it first by default)
FRAME_BATCH=${FRAME_BATCH:-64}
FRAME_LR=${FRAME_LR:-1e-3}
FRAME_TARGETS=${FRAME_TARGETS:-lit}  # stage 1 labels: lit (what a frame shows) or state
LANE_MINUTES=${LANE_MINUTES:-8}      # stage 2
LANE_STEPS=${LANE_STEPS:-1000000}
LANES=${LANES:-32}
SEQ_LEN=${SEQ_LEN:-12}
LANE_LR=${LANE_LR:-5e-4}
LANE_FREEZE=${LANE_FREEZE:-1}        # 1: stage 2 trains only the ConvLSTM and the heads
VAL_EVERY=${VAL_EVERY:-500}          # steps between validations in stage 1 (stage 2: / 4)
VAL_SEQUENCES=${VAL_SEQUENCES:-128}
VAL_LEN=${VAL_LEN:-48}
TEST_TRACKS=${TEST_TRACKS:-240}
TEST_FRAMES=${TEST_FRAMES:-150}
ANNEAL=${ANNEAL:-0.3}             # final share of each stage with a cosine LR decay
PRECISION=${PRECISION:-auto}         # --precision: auto = bf16 where the CPU has AVX512-BF16
THREADS=${THREADS:-2}
FRAME_ARGS=${FRAME_ARGS:-}           # extra `signal-light train` options for stage 1 only
LIT_MAPS=${LIT_MAPS:-0}              # 1: render the pools with --lit-maps
OBLIQUE=${OBLIQUE:-0}                # share of the pools' front and rear views turned

mkdir -p "$RUN" "$DATA"
start=$(date +%s)
echo "== 1/4 data: pool (seeds $POOL_SEEDS), short-track pool (seeds $FRAME_POOL_SEEDS)," \
  "validation (seed $VAL_SEED), test (seed $TEST_SEED) in $DATA"
pools=()        # both stages
frame_pools=()  # stage 1 only
pids=()
map_flag=""
[[ "$LIT_MAPS" == 1 ]] && map_flag=--lit-maps
render_pool() {  # render_pool SEED TRACKS FRAMES: one pool split in the background
  if [[ ! -f "$DATA/pool_$1/manifest.json" ]]; then
    python -m signal_light_node.data.split "$DATA/pool_$1" --seed "$1" \
      --sequences "$2" --seq-len "$3" --full-tracks --overwrite --oblique "$OBLIQUE" $map_flag \
      > "$DATA/pool_$1.log" 2>&1 &
    pids+=($!)
  fi
}
for seed in $POOL_SEEDS; do
  pools+=(--pool "$DATA/pool_$seed")
  render_pool "$seed" "$POOL_TRACKS" "$POOL_FRAMES"
done
for seed in $FRAME_POOL_SEEDS; do
  frame_pools+=(--pool "$DATA/pool_$seed")
  render_pool "$seed" "$FRAME_POOL_TRACKS" "$FRAME_POOL_FRAMES"
done
python - "$DATA" "$VAL_SEED" "$VAL_SEQUENCES" "$VAL_LEN" "$TEST_SEED" "$TEST_TRACKS" "$TEST_FRAMES" <<'EOF'
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

for pid in "${pids[@]}"; do wait "$pid"; done
if [[ -n "${DATA_ONLY:-}" ]]; then
  echo "== DATA_ONLY set: splits ready in $DATA"
  exit 0
fi

# shellcheck disable=SC2206  # TRAIN_ARGS is split into words on purpose
common=(--seed "$SEED" --val-split "$DATA/val_split" --threads "$THREADS" --workers 0
        --anneal-fraction "$ANNEAL" --precision "$PRECISION" "${pools[@]}" $TRAIN_ARGS)
stage() {  # stage NAME MINUTES STEPS ARGS...: train unless it finished; resume if interrupted
  local name=$1 minutes=$2 steps=$3
  shift 3
  if [[ -f "$RUN/$name/summary.json" ]]; then
    echo "$RUN/$name/summary.json exists: finished before; skipping"
    return
  fi
  local resume=()
  if [[ -f "$RUN/$name/last.pt" && -f "$RUN/$name/last.state.pt" ]]; then
    resume=(--resume)   # an interrupted stage continues (with a fresh time budget)
  fi
  signal-light train --out "$RUN/$name" --max-minutes "$minutes" --steps "$steps" \
    "${common[@]}" "$@" "${resume[@]}"
}

echo "== 2/4 stage 1: single frames for $FRAME_MINUTES minutes (batch $FRAME_BATCH)"
stage frames "$FRAME_MINUTES" "$FRAME_STEPS" --mode frames --batch "$FRAME_BATCH" --lr "$FRAME_LR" \
  --frame-targets "$FRAME_TARGETS" --val-every "$VAL_EVERY" "${frame_pools[@]}" $FRAME_ARGS
echo "== 2/4 stage 2: lanes for $LANE_MINUTES minutes ($LANES lanes x $SEQ_LEN frames)"
freeze=()
if [[ "$LANE_FREEZE" == 1 ]]; then
  freeze=(--freeze-encoder)
fi
stage lanes "$LANE_MINUTES" "$LANE_STEPS" --mode lanes --batch "$LANES" --seq-len "$SEQ_LEN" \
  --lr "$LANE_LR" --val-every "$(( VAL_EVERY / 4 > 0 ? VAL_EVERY / 4 : 1 ))" \
  --init-from "$RUN/frames/best.pt" "${freeze[@]}"

echo "== 3/4 best checkpoint -> $WEIGHTS"
mkdir -p "$(dirname "$WEIGHTS")"
# Stage 2's best, by the sequential validation score the node's use calls for; stage 1 is
# validated frame by frame from a zero state, a score of another kind.
cp "$RUN/lanes/best.pt" "$WEIGHTS"

echo "== 4/4 evaluation on the held-out test split"
signal-light evaluate --checkpoint "$WEIGHTS" --split "$DATA/test_split" \
  --out "$RUN/test_eval" --threads "$THREADS"

echo "== done in $(( ($(date +%s) - start) / 60 )) minutes; report: $RUN/test_eval/metrics.md"
