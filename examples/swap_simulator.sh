#!/usr/bin/env bash
# The same episode on PyBullet and, if SAPIEN is installed (pip install 'msmem[sapien]'), on SAPIEN:
# only the simulator changes (--sim, or `simulator: {name: sapien}` in a config file).
#   examples/swap_simulator.sh [STEPS] [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
MSMEM=${MSMEM:-.venv/bin/msmem}
PY=${PY:-.venv/bin/python}
STEPS=${1:-3}
OUT=${2:-runs/swap}
CONFIG=$(mktemp --suffix=.yaml)
trap 'rm -f "$CONFIG"' EXIT
cat > "$CONFIG" <<'YAML'
camera: {width_px: 160, height_px: 120}
scene: {generator: {require_hard: false}}
YAML
sims=(pybullet)
if "$PY" -c "import sapien" 2>/dev/null; then sims+=(sapien); else echo "SAPIEN not installed: pip install 'msmem[sapien]' to compare"; fi
for sim in "${sims[@]}"; do
  "$MSMEM" run --quiet --no-report --config "$CONFIG" --scene-seed 3 --seed 0 --steps "$STEPS" --sim "$sim" --out "$OUT/$sim"
done
"$PY" - "$OUT" "${sims[@]}" <<'PYTHON'
import json, sys
out, sims = sys.argv[1], sys.argv[2:]
keys = ("occupancy_iou", "observable_iou", "semantic_miou", "position_change_m", "seconds_per_step")
print(f"{'simulator':<10}" + "".join(f"{k:>19}" for k in keys))
for sim in sims:
    m = json.load(open(f"{out}/{sim}/metrics.json"))
    print(f"{sim:<10}" + "".join(f"{m[k]:>19.3f}" for k in keys))
PYTHON
