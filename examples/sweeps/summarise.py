"""One markdown table of several `msmem bench` folders of the same method (a sweep), each row paired
against the first folder on the scenes both finished.

    .venv/bin/python examples/sweeps/summarise.py runs/tune10-zeta/a-defaults runs/tune10-zeta/b-cdc0.3 ...

Columns: the paper's metrics per scene (mean ± 95% t-interval; suite-cumulative in brackets), the
paired difference of each against the first folder (* = the interval excludes 0), Position Change,
actions per episode, grasp success and falls.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from msmem_core.run.bench import mean_ci, read_bench_folder, successes


def fmt(values: list[float], star: bool = False, sign: bool = False) -> str:
    m, h = mean_ci(values)
    mark = "*" if star and abs(m) > h else ""
    return f"{m:+.3f} ± {h:.3f}{mark}" if sign else f"{m:.3f} ± {h:.3f}"


def main(folders: list[str]) -> None:
    runs = [(Path(f).name, {s: m for (_, s), m in read_bench_folder(Path(f)).items()}, Path(f)) for f in folders]
    base_name, base, _ = runs[0]
    print("| config | episodes | occupancy mIoU (paper) | semantic mIoU 2-D (paper) | paired occ / sem 2-D against "
          f"{base_name} | Position Change (m) | pushes / grasps | grasp success | episodes with a fall |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, eps, folder in runs:
        scenes = sorted(eps)
        cum = {}
        res = folder / "results.json"
        if res.exists():
            table = json.loads(res.read_text())["summary"]["table"]
            cum = next(iter(table.values())).get("cumulative", {})
        occ = [eps[s]["occupancy_miou"] for s in scenes]
        sem = [eps[s]["semantic_miou_2d"] for s in scenes]
        both = [s for s in scenes if s in base]
        paired = "-" if folder == runs[0][2] else (
            fmt([eps[s]["occupancy_miou"] - base[s]["occupancy_miou"] for s in both], True, True) + " / "
            + fmt([eps[s]["semantic_miou_2d"] - base[s]["semantic_miou_2d"] for s in both], True, True))
        pushes = sum(eps[s]["pushes"] for s in scenes) / len(scenes)
        grasps = sum(eps[s]["grasps"] for s in scenes) / len(scenes)
        n_grasp = sum(eps[s]["grasps"] for s in scenes)
        ok_grasp = sum(successes(eps[s], "grasp") for s in scenes)
        falls = sum(1 for s in scenes if eps[s].get("fell"))
        cum_txt = (f" ({cum['occupancy_miou']:.3f})", f" ({cum['semantic_miou_2d']:.3f})") if cum else ("", "")
        print(f"| {name} | {len(scenes)} | {fmt(occ)}{cum_txt[0]} | {fmt(sem)}{cum_txt[1]} | {paired} | "
              f"{fmt([eps[s]['position_change_m'] for s in scenes])} | {pushes:.1f} / {grasps:.1f} | "
              f"{ok_grasp} of {n_grasp} | {falls} of {len(scenes)} |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    main(ap.parse_args().folders)
