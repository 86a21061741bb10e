#!/usr/bin/env bash
# Render the training and evaluation splits of the training scripts into DATA, once:
# POOL_SEEDS pools of POOL_TRACKS whole tracks (style families 0 and 1), one worker process
# per pool, and beside them the validation split (windows), the own test split and the
# held-out family test split (style family 2), plus a family-2 calibration split when
# CAL_TRACKS > 0 and, when NIGHT_NEGATIVE_TRACKS > 0, family-2 night negatives
# (family_night_negatives, seed NIGHT_NEGATIVE_SEED): night scenes whose every lit vehicle
# glares with tail lamps as bright as a brake, the hard case that bounds the brake's ON
# offset in calibration (training.night_bound; its brakes are labelled as usual). OBLIQUE (default 0) is the share of the pools' front and rear views drawn
# turned (synth.traffic.OBLIQUE_YAW_DEG), TAIL_GLARE (default 0) the share of their lit
# dusk and night vehicles with clipped tail lamps (synth.traffic.Vehicle.glare), REAR_BAR
# (default 0) the share of their rear views with a full-width tail bar (synth.lamps.tail_bar),
# WIDE_TRUCK_LAMPS (default 0) that of their truck and bus rear views with wider clusters,
# NIGHT_STREAK (default 0) that of their dusk and night scenes whose camera smears clipped
# light along its row (synth.camera.CameraParams.streak), NIGHT_CLIP (default 0) that of
# their night scenes whose camera exposes for a lit street and clips its lamps white
# (synth.camera.CameraParams.white_clip), NIGHT_BLOOM (default 0) that of their dusk and
# night scenes whose camera spreads clipped light into a round halo
# (synth.camera.CameraParams.bloom), GLARE_TAIL_HOT (default 0) that of their
# TAIL_GLARE vehicles whose tail lamps' core and glow are drawn at their brake's colour
# (synth.traffic.Vehicle.tail_hot), GLARE_TAIL_BRIGHT (default 0) that of their TAIL_GLARE
# vehicles whose tail lamps shine as brightly as another vehicle's brake, their brake
# brighter still (synth.traffic.BRIGHT_TAIL_LEVEL), FOREIGN_LAMP (default 0) that of their
# vehicles with a lamp beyond them, over the roof or beside, inside their crop
# (synth.foreign_lamps: steady or switching red, flashing amber, white), FOREIGN_HIGH
# (default 0) that of those lamps drawn red over the middle of the roof, where a centre
# high-mounted stop lamp would be, BRAKE_SHARE (default 0: the renderer's own, about 40 %)
# the share of the time a brake is pressed and of tracks first seen braking
# (synth.lamps.brake_timeline), TURN_HUE (default 0) that of their vehicles whose blinkers,
# and the amber markers that match them, shine in a random hue
# (synth.lamps.recolour_turn_lamps); the evaluation splits never have any
# of them, so that they stay comparable across data versions.
# TRUTH_RULE (default lamp; synth.truth.TRUTH_RULES) labels every split, pools and evaluation
# splits alike: data of another rule is another data version, and a model trained on it is
# scored against models of the old one on this DATA's evaluation splits.
# CROP_FILL=1 (default 0) cuts every split, pools and evaluation splits alike, with
# crops.CropConfig.fill (the grown box stretched to the square): data for a model with
# "crop_fill": true, another data version (docs/model.md, "Crops that fill the square").
# POOL_NAME (default pool) names the pools DATA/POOL_NAME_SEED, so that pools of the same
# seeds drawn with other settings (train_trunk.sh's glare pools) can sit beside them.
# A split whose manifest exists is reused. Called by train_default.sh and train_trunk.sh
# with their settings in the environment (the defaults are theirs).
set -euo pipefail

cd "$(dirname "$0")/.."
: "${DATA:?DATA must name the data directory}"
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
CAL_TRACKS=${CAL_TRACKS:-0}
NIGHT_NEGATIVE_SEED=${NIGHT_NEGATIVE_SEED:-960001}
NIGHT_NEGATIVE_TRACKS=${NIGHT_NEGATIVE_TRACKS:-0}
OBLIQUE=${OBLIQUE:-0}
TAIL_GLARE=${TAIL_GLARE:-0}
REAR_BAR=${REAR_BAR:-0}
WIDE_TRUCK_LAMPS=${WIDE_TRUCK_LAMPS:-0}
NIGHT_STREAK=${NIGHT_STREAK:-0}
NIGHT_CLIP=${NIGHT_CLIP:-0}
NIGHT_BLOOM=${NIGHT_BLOOM:-0}
GLARE_TAIL_HOT=${GLARE_TAIL_HOT:-0}
GLARE_TAIL_BRIGHT=${GLARE_TAIL_BRIGHT:-0}
FOREIGN_LAMP=${FOREIGN_LAMP:-0}
FOREIGN_HIGH=${FOREIGN_HIGH:-0}
BRAKE_SHARE=${BRAKE_SHARE:-0}
TURN_HUE=${TURN_HUE:-0}
TRUTH_RULE=${TRUTH_RULE:-lamp}
POOL_NAME=${POOL_NAME:-pool}
CROP_FILL=${CROP_FILL:-0}
fill=()
[[ "$CROP_FILL" == 1 ]] && fill=(--crop-fill)

mkdir -p "$DATA"
pids=()
for seed in $POOL_SEEDS; do
  pool="$DATA/${POOL_NAME}_$seed"
  if [[ ! -f "$pool/manifest.json" ]]; then
    python -m signal_light_node.data.split "$pool" --seed "$seed" \
      --sequences "$POOL_TRACKS" --seq-len "$POOL_FRAMES" --full-tracks --overwrite \
      --oblique "$OBLIQUE" --tail-glare "$TAIL_GLARE" --rear-bar "$REAR_BAR" \
      --wide-truck-lamps "$WIDE_TRUCK_LAMPS" --night-streak "$NIGHT_STREAK" \
      --night-clip "$NIGHT_CLIP" --night-bloom "$NIGHT_BLOOM" \
      --glare-tail-hot "$GLARE_TAIL_HOT" --glare-tail-bright "$GLARE_TAIL_BRIGHT" \
      --foreign-lamp "$FOREIGN_LAMP" --foreign-high "$FOREIGN_HIGH" \
      --brake-share "$BRAKE_SHARE" \
      --turn-hue "$TURN_HUE" \
      --truth-rule "$TRUTH_RULE" "${fill[@]}" \
      > "$pool.log" 2>&1 &
    pids+=($!)
  fi
done
python - "$DATA" "$VAL_SEED" "$VAL_SEQUENCES" "$VAL_LEN" "$TEST_SEED" "$FAMILY_SEED" \
  "$TEST_TRACKS" "$TEST_FRAMES" "$CAL_SEED" "$CAL_TRACKS" "$TRUTH_RULE" \
  "$NIGHT_NEGATIVE_SEED" "$NIGHT_NEGATIVE_TRACKS" "$CROP_FILL" <<'PY'
import sys
from pathlib import Path

from signal_light_node.data.split import write_split
from signal_light_node.model import ModelConfig
from signal_light_node.synth.lamps import HELD_OUT_FAMILY

(run, val_seed, val_n, val_len, test_seed, family_seed, test_n, test_len, cal_seed, cal_n, rule,
 neg_seed, neg_n, crop_fill) = sys.argv[1:]
crop = ModelConfig(crop_fill=crop_fill == "1").crop_config()
# name, seed, items, length, whole tracks, renderer overrides, stream options
held_out = {"family": HELD_OUT_FAMILY}
splits = [("val_split", val_seed, val_n, val_len, False, {}, {}),
          ("test_split", test_seed, test_n, test_len, True, {}, {}),
          ("family_test_split", family_seed, test_n, test_len, True, held_out, {})]
if int(cal_n) > 0:
    splits.append(("family_cal_split", cal_seed, cal_n, test_len, True, held_out, {}))
if int(neg_n) > 0:
    glare = dict(held_out, tail_glare=1.0, glare_tail_bright=1.0)
    splits.append(("family_night_negatives", neg_seed, neg_n, test_len, True, glare,
                   {"lighting": "night"}))
for name, seed, n, length, full, overrides, options in splits:
    out = Path(run) / name
    if (out / "manifest.json").is_file():
        print(f"{out} exists; reusing it")
        continue
    overrides = dict(overrides)
    if rule != "lamp":
        overrides["truth_rule"] = rule
    extra = {"renderer_overrides": overrides} if overrides else {}
    write_split(out, seed=int(seed), n_sequences=int(n), seq_len=int(length), crop=crop,
                full_tracks=full, progress=False, **extra, **options)
PY
for pid in "${pids[@]}"; do wait "$pid"; done
