"""Table I (the paper's metrics, Position Change, actions) and the paper's claims, from one `msmem bench`
folder with the five methods.

    .venv/bin/python examples/table1.py runs/hard25-map

Per method: the paper's metrics per scene (mean ± 95% t-interval, suite-cumulative in brackets),
Position Change, pushes and grasps per episode, grasp success, episodes with a fall, and the paper's
Table I beside. Then the claims the issue checks, each on the scenes both methods finished: "A above B"
holds when the paired interval lies above 0; Position Change ratios are of the means.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from msmem_core.run.bench import mean_ci, read_bench_folder, successes

METHODS = ("ours", "no-cdc", "push-only", "grasp-only", "view-only")
PAPER = {"ours": (0.899, 0.767, 0.707), "no-cdc": (0.905, 0.791, 1.231), "push-only": (0.887, 0.756, 1.571),
         "grasp-only": (0.880, 0.681, 0.228)}
"""The paper's Table I: occupancy IoU, semantic IoU, Position Change (m)."""


def load(folder: Path) -> tuple[dict[str, dict[int, dict]], dict]:
    eps: dict[str, dict[int, dict]] = {}
    for (method, scene), metrics in read_bench_folder(folder).items():
        eps.setdefault(method, {})[scene] = metrics
    res = folder / "results.json"
    table = json.loads(res.read_text())["summary"]["table"] if res.exists() else {}
    return eps, table


def ci(values: list[float], sign: bool = False) -> str:
    m, h = mean_ci(values)
    return f"{m:+.3f} ± {h:.3f}" if sign else f"{m:.3f} ± {h:.3f}"


def main(folder: Path) -> None:
    eps, table = load(folder)
    methods = [m for m in METHODS if m in eps]
    print("| method | episodes | occupancy mIoU (paper) | semantic mIoU 2-D (paper) | Position Change (m) | "
          "pushes / grasps per episode | grasp success | episodes with a fall | paper: occ / sem / PC |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in methods:
        e = eps[m]
        s = sorted(e)
        cum = table.get(m, {}).get("cumulative", {})
        occ = ci([e[i]["occupancy_miou"] for i in s]) + (f" ({cum['occupancy_miou']:.3f})" if cum else "")
        sem = ci([e[i]["semantic_miou_2d"] for i in s]) + (f" ({cum['semantic_miou_2d']:.3f})" if cum else "")
        n_grasp = sum(e[i]["grasps"] for i in s)
        ok = sum(successes(e[i], "grasp") for i in s)
        paper = " / ".join(f"{v:.3f}" for v in PAPER[m]) if m in PAPER else ""
        print(f"| {m} | {len(s)} | {occ} | {sem} | {ci([e[i]['position_change_m'] for i in s])} | "
              f"{sum(e[i]['pushes'] for i in s) / len(s):.1f} / {n_grasp / len(s):.2f} | "
              f"{f'{ok} of {n_grasp}' if n_grasp else '-'} | {sum(1 for i in s if e[i].get('fell'))} of {len(s)} | "
              f"{paper} |")
    print()
    print("| claim (the paper's) | measured (paired over scenes) | holds |")
    print("|---|---|---|")
    for a in ("ours", "no-cdc"):
        for b in ("push-only", "grasp-only"):
            for key, name in (("occupancy_miou", "occupancy mIoU"), ("semantic_miou_2d", "2-D semantic mIoU")):
                if a not in eps or b not in eps:
                    continue
                both = sorted(set(eps[a]) & set(eps[b]))
                d = [eps[a][i][key] - eps[b][i][key] for i in both]
                mean, half = mean_ci(d)
                verdict = "yes" if mean - half > 0 else ("no (below, significant)" if mean + half < 0 else
                                                         "not shown (interval includes 0)")
                print(f"| {a} above {b} on {name} | {ci(d, True)} ({len(both)} scenes) | {verdict} |")
    for b, limit in (("no-cdc", 0.6), ("push-only", 0.5)):
        if "ours" in eps and b in eps:
            both = sorted(set(eps["ours"]) & set(eps[b]))
            po = sum(eps["ours"][i]["position_change_m"] for i in both) / len(both)
            pb = sum(eps[b][i]["position_change_m"] for i in both) / len(both)
            ratio = po / pb if pb > 0 else float("inf")
            print(f"| ours' Position Change at most {limit}x {b}'s | {po:.3f} / {pb:.3f} m = {ratio:.2f}x | "
                  f"{'yes' if ratio <= limit else 'no'} |")
    if "ours" in eps and "no-cdc" in eps:
        both = sorted(set(eps["ours"]) & set(eps["no-cdc"]))
        d = [eps["ours"][i]["semantic_miou_2d"] - eps["no-cdc"][i]["semantic_miou_2d"] for i in both]
        mean, _ = mean_ci(d)
        print(f"| ours within 0.01 of no-cdc on 2-D semantic mIoU | {ci(d, True)} | "
              f"{'yes' if abs(mean) <= 0.01 else 'no'} (mean) |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    main(ap.parse_args().folder)
