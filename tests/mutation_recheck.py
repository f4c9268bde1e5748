"""Re-run mutmut's unsettled mutants one at a time, each in its own plain pytest process.

    .venv/bin/python tests/mutation_recheck.py [--status suspicious] [--module msmem_core.map.belief] [--tests FILE ...]

Inside mutmut 3's fork server some of this project's tests end with SIGTERM (exit -15, reported as
"suspicious") though the same mutant run under plain pytest passes or fails cleanly (docs/
reliability.md, "Mutation testing of the math"). This runs each such mutant's tests (mutmut's own
test mapping, ``mutants/mutmut-stats.json``) with ``MUTANT_UNDER_TEST`` set, in ``mutants/``, and
prints killed (a test failed), survived (all passed) or timeout per mutant and a summary. Needs a
finished ``mutmut run`` (``make mutation``).

Plugin modules: mutmut names their mutants by path (``plugins.msmem_grasp.vmf.x_...``) and finds no
tests for them, because the tests import the module as ``msmem_grasp.vmf`` and the trampoline
compares the mutant's module with the function's ``__module__``. Here the ``plugins.`` prefix is
dropped from ``MUTANT_UNDER_TEST`` (the test run imports ``mutants/plugins/*`` first, tests/conftest.py),
so give their tests with ``--tests``, e.g. ``--status "no tests" --module plugins.msmem_grasp.vmf
--tests tests/test_vmf.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MUTANTS = ROOT / "mutants"


def unsettled(status: str, module: str) -> list[str]:
    out = subprocess.run([str(ROOT / ".venv/bin/mutmut"), "results", "--all", "true"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    names = []
    for line in out.splitlines():
        name, _, st = line.strip().rpartition(": ")
        if st == status and name.startswith(module):
            names.append(name)
    return names


def tests_of(name: str, stats: dict) -> list[str]:
    func = name.rsplit("__mutmut_", 1)[0]
    return sorted(stats["tests_by_mangled_function_name"].get(func, []))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--status", default="suspicious")
    ap.add_argument("--module", default="msmem_core.")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per mutant")
    ap.add_argument("--tests", nargs="*", default=None,
                    help="run these test files instead of mutmut's mapping (for tests added since its run)")
    ap.add_argument("-k", dest="keyword", default=None, help="pytest -k expression for --tests")
    args = ap.parse_args()
    stats = json.loads((MUTANTS / "mutmut-stats.json").read_text())
    names = unsettled(args.status, args.module)
    counts: Counter[str] = Counter()
    for i, name in enumerate(names, 1):
        tests = args.tests if args.tests is not None else tests_of(name, stats)
        env = {**os.environ, "MUTANT_UNDER_TEST": name.removeprefix("plugins.")}
        try:
            extra = ["-k", args.keyword] if args.keyword else []
            rc = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:randomly", *extra, *tests],
                                cwd=MUTANTS, env=env, capture_output=True, timeout=args.timeout).returncode
            verdict = "survived" if rc == 0 else "killed" if rc == 1 else f"error (rc {rc})"
        except subprocess.TimeoutExpired:
            verdict = "timeout"
        counts[verdict] += 1
        print(f"[{i}/{len(names)}] {name}: {verdict}", flush=True)
    print(", ".join(f"{k} {v}" for k, v in sorted(counts.items())))


if __name__ == "__main__":
    main()
