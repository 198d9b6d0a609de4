#!/usr/bin/env bash
# Which hard-room condition moves the segmentation figures most: make the same few subjects
# with each condition of configs/synth_hard.yaml alone (and with none, and with all), then
# score main's segmentation (library defaults and configs/benchmark.yaml) on each set.
#
#   bash benchmarks/ablate_hard_rooms.sh OUT [N] [SEED]     # defaults: N=3, SEED=3000
#
# Writes OUT/<condition>/subject_*/ and OUT/<condition>_<defaults|benchmark>.txt (the output
# of benchmarks/eval_synth_segmentation.py; its "pooled" row holds F and the cast shadow kept
# as background). The conditions draw from their own random streams, so every set shows the
# same bodies, postures and cameras; stereo pairs are not made (they do not change the posture
# images).
set -euo pipefail
out=${1:?usage: ablate_hard_rooms.sh OUT [N] [SEED]}
n=${2:-3}
seed=${3:-3000}
py=${PYTHON:-python}
declare -A sets=(
  [standard]=""
  [wall_shadows]="--set wall_shadows=true"
  [furniture]="--set furniture=true"
  [textures]="--set textures=true"
  [exposure]="--set exposure_change=0.1 --set white_balance=0.06 --set exposure_drift=0.05"
  [noise_jpeg]="--set noise_sigma=4.0 --set jpeg_quality=[75,90]"
  [camera]="--set camera_distance_m=[2.5,5.0] --set camera_height_m=[0.8,2.0]"
  [all]="--config configs/synth_hard.yaml"
)
for name in standard wall_shadows furniture textures exposure noise_jpeg camera all; do
  if [ ! -f "$out/$name/done" ]; then
    # shellcheck disable=SC2086
    $py tools/make_subjects.py --out "$out/$name" --n "$n" --seed "$seed" --set stereo=false \
      ${sets[$name]}
    touch "$out/$name/done"
  fi
  $py benchmarks/eval_synth_segmentation.py --data "$out/$name" --quiet \
    > "$out/${name}_defaults.txt"
  $py benchmarks/eval_synth_segmentation.py --data "$out/$name" --quiet \
    --config configs/benchmark.yaml > "$out/${name}_benchmark.txt"
done
grep -H "^pooled" "$out"/*_defaults.txt "$out"/*_benchmark.txt
