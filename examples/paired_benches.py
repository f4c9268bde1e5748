"""Paired per-scene differences between `msmem bench` folders run with different configs.

    .venv/bin/python examples/paired_benches.py runs/map-bench/cnabu-map runs/map-bench/analytic \
        runs/map-bench/column-fill

The first folder is compared with each of the others on the scenes both finished (same method and
scene index), metric by metric: mean of (first - other) and the half-width of its 95% t-interval
(`msmem_core.run.bench.mean_ci`); an interval excluding 0 is marked *. Suite-cumulative paper metrics
of each folder are printed too (from `results.json`), and their differences with a paired bootstrap
interval (`cumulative_difference`).

    .venv/bin/python examples/paired_benches.py --within ours view-only runs/t-ours

``--within A B``: in each folder given, method A minus method B on the scenes both finished.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from msmem_core.run.bench import cumulative_difference, mean_ci, read_bench_folder, read_paper_counts

METRICS = ("occupancy_miou", "semantic_miou_2d", "observable_iou", "occupancy_iou", "semantic_miou", "occupancy_nll",
           "semantic_nll",
           "occupancy_ece", "semantic_ece")


def main(folders: list[str]) -> None:
    first, *others = (Path(f) for f in folders)
    base = read_bench_folder(first)
    print("| folder | episodes | " + " | ".join(METRICS) + " (suite-cumulative: occupancy mIoU, semantic mIoU 2-D) |")
    print("|---|---|" + "---|" * len(METRICS))
    for folder in (first, *others):
        eps = read_bench_folder(folder)
        cells = []
        for k in METRICS:
            m, c = mean_ci([e[k] for e in eps.values() if k in e])
            cells.append(f"{m:.3f} ± {c:.3f}")
        cum = json.loads((folder / "results.json").read_text())["summary"]["table"]
        cum_cells = ", ".join(f"{v.get('cumulative', {}).get('occupancy_miou', float('nan')):.3f} / "
                              f"{v.get('cumulative', {}).get('semantic_miou_2d', float('nan')):.3f}"
                              for v in cum.values())
        print(f"| {folder.name} | {len(eps)} | " + " | ".join(cells) + f" | {cum_cells} |")
    print()
    print(f"Paired differences, {first.name} minus each (mean ± 95% CI over scenes; * = interval excludes 0):")
    print()
    print("| difference | scenes | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for folder in others:
        other = read_bench_folder(folder)
        keys = sorted(set(base) & set(other))
        cells = []
        for k in METRICS:
            m, c = mean_ci([base[s][k] - other[s][k] for s in keys if k in base[s] and k in other[s]])
            star = "*" if not math.isnan(c) and abs(m) > c else ""
            cells.append(f"{m:+.3f} ± {c:.3f}{star}")
        print(f"| {first.name} - {folder.name} | {len(keys)} | " + " | ".join(cells) + " |")
    print()
    print(f"Suite-cumulative paper metrics, {first.name} minus each (paired bootstrap over scenes, 2,000 draws,")
    print("95% percentile interval; * = interval excludes 0):")
    print()
    print("| difference | occupancy mIoU | semantic mIoU 2-D |")
    print("|---|---|---|")
    base_counts = read_paper_counts(first)
    methods = {m for m, _ in base}
    only = next(iter(methods)) if len(methods) == 1 else None  # the same method in a folder of several
    for folder in others:
        counts = read_paper_counts(folder, only)
        cells = []
        for k in ("occupancy_miou", "semantic_miou_2d"):
            d, lo, hi = cumulative_difference(base_counts, counts, k)
            cells.append(f"{d:+.3f} [{lo:+.3f}, {hi:+.3f}]{'*' if lo > 0 or hi < 0 else ''}")
        print(f"| {first.name} - {folder.name} | " + " | ".join(cells) + " |")


def within(a: str, b: str, folders: list[str]) -> None:
    print(f"Paired differences, {a} minus {b} in each folder (mean ± 95% CI over scenes; * = interval excludes 0):")
    print()
    print("| folder | scenes | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for f in folders:
        eps = read_bench_folder(Path(f))
        scenes = sorted({s for m, s in eps if m == a} & {s for m, s in eps if m == b})
        cells = []
        for k in METRICS:
            d = [eps[(a, s)][k] - eps[(b, s)][k] for s in scenes if k in eps[(a, s)] and k in eps[(b, s)]]
            m, c = mean_ci(d)
            star = "*" if not math.isnan(c) and abs(m) > c else ""
            cells.append(f"{m:+.3f} ± {c:.3f}{star}")
        print(f"| {Path(f).name} | {len(scenes)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", help="`msmem bench --out` folders; the first is compared with the others")
    ap.add_argument("--within", nargs=2, metavar=("A", "B"), help="compare method A with method B inside each folder")
    args = ap.parse_args()
    if args.within:
        within(*args.within, args.folders)
    else:
        main(args.folders)
