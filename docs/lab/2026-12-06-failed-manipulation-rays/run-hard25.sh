#!/usr/bin/env bash
# hard25, measured only: the 15 Table I episodes with a failed manipulation (docs/results/table1), under
# disturbed_rays: failed, and no-cdc's five under the defaults (the step records of grasp-only's and
# ours's are in docs/lab/2026-12-06-failed-grasps/runs). Every other Table I episode has no failed
# manipulation, and the option acts only after one, so those are the same under it. Resumable.
set -euo pipefail
L=docs/lab/2026-12-06-failed-manipulation-rays
MSMEM=${MSMEM:-msmem}
{
  for s in 00 04 09 18; do echo "failed-rays grasp-only $s $L/configs/failed-rays.yaml"; done
  for s in 00 01 04 09 18; do echo "failed-rays no-cdc $s $L/configs/failed-rays.yaml"; done
  for s in 00 03 04 08 09 18; do echo "failed-rays ours $s $L/configs/failed-rays.yaml"; done
  for s in 00 01 04 09 18; do echo "defaults no-cdc $s $L/configs/one-thread.yaml"; done
} | xargs -P 2 -L 1 bash -c '
  out='"$L"'/runs-hard25/$0/$1/scene$2
  [ -f "$out/metrics.json" ] && exit 0
  '"$MSMEM"' run -m "$1" -c "$3" --scene msmem_core/suites/hard25/scene_$2.json --steps 40 --no-report \
      --out "$out" > /dev/null 2>&1 || echo "failed: $out"
'
