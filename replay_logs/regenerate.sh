#!/usr/bin/env bash
# Regenerate the bundled replay logs from the SITL (deterministic from the seeds below).
# Usage (from anywhere): replay_logs/regenerate.sh [NAME ...]   (default: all)
# Each run writes the simulation straight to MCAP (no transports), truth embedded.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$here")"
python="${PYTHON:-$root/.venv/bin/python}"

declare -A ARGS=(
  [wall_survey]="--scene wall --pilot script:survey --seed 1 --gust-rate 4"
  [pillar_survey]="--scene pillar --pilot script:survey --seed 2 --gust-rate 2"
  [wall_slow_touch_gusts]="--scene wall --pilot script:slow_touch --seed 3 --gust-rate 12"
)
names=("$@")
if [ ${#names[@]} -eq 0 ]; then names=(wall_survey pillar_survey wall_slow_touch_gusts); fi
for name in "${names[@]}"; do
  if [ -z "${ARGS[$name]+x}" ]; then
    echo "unknown log '$name' (known: ${!ARGS[*]})" >&2
    exit 2
  fi
  out="${OUT_DIR:-$here}/$name.mcap"
  # shellcheck disable=SC2086
  (cd "$root" && "$python" -m groundstation.cli sitl ${ARGS[$name]} --speed max --record "$out" --force)
done
