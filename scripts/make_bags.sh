#!/usr/bin/env bash
# Regenerate the committed scene bags in bags/ and check their coverage.
#
#   bash scripts/make_bags.sh            (after `make setup`; sources env.sh itself)
#
# Each bag is ~10 s of a 640x360 scene at 12 Hz with JPEG frames, written by
# `signal-light synth`; the seeds were chosen with `scripts/bag_coverage.py --search` so
# that every view, every intent and brake ON and OFF occur with at least 4 vehicles.
# The output is deterministic: the same code and options give the same bags. When the
# renderer changes, the check at the end may fail; pick new seeds with e.g.
#   python scripts/bag_coverage.py --search --lighting day --fps 12 --vehicles 6 --seeds 0:30
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
# shellcheck disable=SC1091
[ -n "${VIRTUAL_ENV:-}" ] || source env.sh

COMMON=(--duration 10 --fps 12 --width 640 --height 360 --vehicles 6 --jpeg-quality 80 --overwrite)

signal-light synth -o bags/day_street --seed 13 --lighting day "${COMMON[@]}"
signal-light synth -o bags/night_street --seed 22 --lighting night "${COMMON[@]}"

python scripts/bag_coverage.py bags/day_street bags/night_street
du -sh bags
