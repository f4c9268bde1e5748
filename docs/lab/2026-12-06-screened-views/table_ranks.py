"""Summary of ``ranks.py`` output files: steps, how often the best view ranks at or beyond K in the
screening's order, and the mean and largest relative IG shortfall of the best of the first K.

    python table_ranks.py runs/ranks-*.jsonl
"""

from __future__ import annotations

import json
import sys

import numpy as np

rows = [json.loads(line) for f in sys.argv[1:] for line in open(f) if line.startswith("{")]
ranks = np.array([r["rank"] for r in rows])
print(f"{len(rows)} steps of {len(sys.argv) - 1} episodes")
print("| finalists K | steps whose best view is not among them | mean IG shortfall | largest |")
print("|---|---|---|---|")
for k in ("8", "16", "32", "64", "128"):
    short = np.array([r["short"][k] for r in rows])
    print(f"| {k} | {(ranks >= int(k)).sum()} | {100 * short.mean():.2f} % | {100 * short.max():.1f} % |")
