#!/usr/bin/env bash
# Step records of tune10, grasp-only and ours, 40 steps, one thread (as the bench runs them), under the
# defaults and under disturbed_rays: failed. Two episodes at a time. Resumable: a finished run folder
# (metrics.json present) is skipped.
set -euo pipefail
L=docs/lab/2026-12-06-failed-manipulation-rays
MSMEM=${MSMEM:-msmem}
jobs=()
for variant in defaults failed-rays; do
  cfg=$L/configs/one-thread.yaml
  [ "$variant" = failed-rays ] && cfg=$L/configs/failed-rays.yaml
  for method in grasp-only ours; do
    for s in 00 01 02 03 04 05 06 07 08 09; do
      jobs+=("$variant $method $s $cfg")
    done
  done
done
printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c '
  out='"$L"'/runs/$0/$1/scene$2
  [ -f "$out/metrics.json" ] && exit 0
  '"$MSMEM"' run -m "$1" -c "$3" --scene msmem_core/suites/tune10/scene_$2.json --steps 40 --no-report \
      --out "$out" > /dev/null 2>&1 || echo "failed: $out"
'
