#!/usr/bin/env bash
# The main job (`make demo`): start the detector node, record what it publishes, play a
# committed bag into it, wait until every frame is processed, stop everything and print
# a report (frames in/out, per-track timelines, latency, annotated video).
#
# Environment knobs (all optional):
#   DEMO_BAG        bag to play (default: bags/day_street, the training renderer's day street;
#                   the first bag under bags/ if it is missing)
#   DEMO_MODEL      checkpoint for the node (default: the shipped weights)
#   DEMO_OUT        output folder (default: out/demo)
#   DEMO_RATE       playback speed factor (default: 1.0)
#   DEMO_DOMAIN_ID  ROS_DOMAIN_ID to use (default: a random one, so demos never clash)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
# shellcheck disable=SC1091
source env.sh

say() { printf '[demo] %s\n' "$*"; }
die() { printf '[demo] error: %s\n' "$*" >&2; exit 1; }

OUT="${DEMO_OUT:-out/demo}"
RATE="${DEMO_RATE:-1.0}"
export ROS_DOMAIN_ID="${DEMO_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

# --- inputs ---------------------------------------------------------------------------
BAG="${DEMO_BAG:-}"
# Named, not the first bag in sort order: the hard-negative bags (day_running_lamps, ...)
# sort before it and hold no signal at all.
if [ -z "$BAG" ] && [ -f bags/day_street/metadata.yaml ]; then BAG=bags/day_street; fi
if [ -z "$BAG" ]; then
  for cand in bags/*; do
    if [ -f "$cand/metadata.yaml" ] || [[ "$cand" == *.mcap ]]; then BAG="$cand"; break; fi
  done
fi
[ -n "$BAG" ] || die "no bag under bags/ (set DEMO_BAG=/path/to/bag)"
[ -e "$BAG" ] || die "bag $BAG does not exist"

MODEL_ARGS=()
if [ -n "${DEMO_MODEL:-}" ]; then
  [ -f "$DEMO_MODEL" ] || die "DEMO_MODEL=$DEMO_MODEL is not a file"
  MODEL_ARGS=(-p "model_path:=$(cd "$(dirname "$DEMO_MODEL")" && pwd)/$(basename "$DEMO_MODEL")")
else
  WEIGHTS="$(python -c 'from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS; print(DEFAULT_WEIGHTS)')"
  [ -f "$WEIGHTS" ] || die "the shipped weights $WEIGHTS do not exist yet; train them (see README, 'signal-light train') or run with DEMO_MODEL=/path/to/checkpoint.pt"
fi

read -r TRANSPORT IMAGE_TOPIC DET_TOPIC FRAMES < <(python -m signal_light_node.tools.demo_report inspect "$BAG") \
  || die "cannot read the input topics of $BAG"
IMAGE_INPUT="~/input/image"
[ "$TRANSPORT" = compressed ] && IMAGE_INPUT="~/input/image/compressed"

mkdir -p "$OUT"
REC="$OUT/output_bag"
rm -rf "$REC"
rm -f "$OUT"/*.log

# --- processes ------------------------------------------------------------------------
PIDS=()
cleanup() {
  # Newest first, one at a time: the recorder stops (and flushes) before the detector goes.
  local pid i
  for (( i=${#PIDS[@]}-1; i>=0; i-- )); do
    pid="${PIDS[$i]}"
    kill -0 "$pid" 2>/dev/null || continue
    kill -INT "$pid" 2>/dev/null || true
    for _ in $(seq 1 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    if kill -0 "$pid" 2>/dev/null; then kill -KILL "$pid" 2>/dev/null || true; fi
  done
  PIDS=()
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# wait_for_line FILE TEXT PID TIMEOUT: poll FILE until it contains TEXT; fail if PID exits.
wait_for_line() {
  local file="$1" text="$2" pid="$3" deadline=$(( SECONDS + $4 ))
  until grep -qF -- "$text" "$file" 2>/dev/null; do
    if ! kill -0 "$pid" 2>/dev/null; then cat "$file" >&2; die "$(basename "$file" .log) exited early (log above)"; fi
    if [ "$SECONDS" -ge "$deadline" ]; then cat "$file" >&2; die "$(basename "$file" .log) not ready after $4 s"; fi
    sleep 0.1
  done
}

say "bag $BAG: $FRAMES frames on $IMAGE_TOPIC ($TRANSPORT) + $DET_TOPIC; ROS_DOMAIN_ID=$ROS_DOMAIN_ID"
# The remap rules are quoted: an unquoted ~/... would be expanded by the shell. A longer
# work queue than the default makes a busy machine delay frames rather than drop them: the
# demo is about an output for every frame (the benchmark measures the live latency).
detector --ros-args --params-file config/detector.yaml "${MODEL_ARGS[@]}" \
  -p image_transport:="$TRANSPORT" -p reliability:=reliable -p work_queue_size:=30 \
  -r "$IMAGE_INPUT:=$IMAGE_TOPIC" -r "~/input/detections:=$DET_TOPIC" \
  > "$OUT/detector.log" 2>&1 &
PIDS+=($!)
wait_for_line "$OUT/detector.log" "ready:" "${PIDS[0]}" 120
say "detector ready (log: $OUT/detector.log)"

signal-light record -o "$REC" --topics /signal_light_detector/output/vehicle_lights /diagnostics \
  > "$OUT/record.log" 2>&1 &
PIDS+=($!)
wait_for_line "$OUT/record.log" "recording all 2 topic(s)" "${PIDS[1]}" 60
say "recording into $REC"

say "playing $BAG at rate $RATE"
signal-light play "$BAG" --topics "$IMAGE_TOPIC" "$DET_TOPIC" --rate "$RATE" \
  --wait-for-subscribers 1 --wait-timeout 60 2> "$OUT/play.log" \
  || { cat "$OUT/play.log" >&2; die "play failed"; }
tail -n 1 "$OUT/play.log" | sed 's/^INFO signal_light_node.play: /[demo] /'

say "waiting for the detector to finish the last frames"
python -m signal_light_node.ros.drain --expect-images "$FRAMES" --timeout 60 \
  || say "warning: the detector did not report all frames done; the report shows what is missing"

cleanup
trap - EXIT

say "writing the annotated video and the report"
python -m signal_light_node.tools.demo_report report --input "$BAG" --output "$REC" --out-dir "$OUT" \
  | tee "$OUT/report.txt"
