"""Score one module's mutants fast: every mutant's tests in a process forked from one that imported them.

    .venv/bin/python tests/mutation_scan.py --generate                      # mutmut's mutants/ only
    .venv/bin/python tests/mutation_scan.py --module msmem_core.map.ig \\
        --tests tests/test_ig.py tests/test_ig_incremental.py tests/test_ig_mutation.py --out ig_scan.jsonl

``mutmut run`` runs each mutant's tests through its fork server, where some of this project's tests die
with SIGTERM ("suspicious", docs/explanation/reliability.md), and finds no tests for plugin modules. This scanner
generates the mutants with mutmut's own code (``--generate``), then, per mutant, forks a child of a
process that has already imported pytest, numpy, numba and the test modules, sets the mutant with
mutmut's ``set_mutant_under_test`` and runs the given test files with ``-x``. A child that does not
finish within ``--timeout`` seconds is killed and counts as killed by timeout (a mutant that loops).

One JSON line per mutant goes to ``--out`` as it finishes (``{"mutant", "status", "seconds"}``), and a
rerun skips the mutants already there, so a long scan resumes. Statuses: ``killed`` (a test failed or
errored), ``survived`` (all passed), ``timeout``. Plant-the-bug check: the scan first runs the tests
with the programmatic failure mutmut uses to verify its set-up, and stops if they pass.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MUTANTS = ROOT / "mutants"


def generate() -> None:
    """mutmut's mutant generation alone (the first phase of ``mutmut run``), into ``mutants/``."""
    os.chdir(ROOT)
    from mutmut import __main__ as mm

    mm.set_mutant_under_test("mutant_generation")
    mm.copy_src_dir()
    mm.copy_also_copy_files()
    mm.setup_source_paths()
    stats = mm.create_mutants(1)
    print(f"mutants generated in {MUTANTS}: {stats.mutated} files mutated, {stats.unmodified} unmodified")


def mutant_names(module: str) -> list[str]:
    """Every mutant of ``module`` (``msmem_core.map.ig`` -> ``mutants/msmem_core/map/ig.py``), in file order."""
    src = (MUTANTS / Path(*module.split("."))).with_suffix(".py").read_text()
    names = re.findall(r"^\s*def (x\S*?__mutmut_\d+)\(", src, flags=re.M)
    return [f"{module}.{n}" for n in dict.fromkeys(names)]


def run_child(name: str, tests: list[str], timeout: float) -> str:
    pid = os.fork()
    if pid == 0:  # child
        try:
            import pytest
            from hypothesis import Phase, settings
            from mutmut.mutation.trampoline import set_mutant_under_test

            # a failing property is not shrunk: the scan wants killed or not, not the smallest example
            settings.register_profile("scan", phases=[Phase.explicit, Phase.reuse, Phase.generate], database=None)
            settings.load_profile("scan")
            # plugin modules: mutmut names them by path, the tests import them without the folder
            set_mutant_under_test(re.sub(r"^(plugins|simulators)\.", "", name))
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            rc = pytest.main(["-x", "-q", "-p", "no:cacheprovider", "-p", "no:randomly", *tests])
            os._exit(0 if rc == 0 else 1)
        except BaseException:
            os._exit(1)
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return "survived" if os.waitstatus_to_exitcode(status) == 0 else "killed"
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return "timeout"
        time.sleep(0.02)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--generate", action="store_true", help="generate mutants/ with mutmut and stop")
    ap.add_argument("--module", default="msmem_core.map.ig")
    ap.add_argument("--tests", nargs="+", default=["tests/test_ig.py"])
    ap.add_argument("--out", type=Path, default=Path("mutation_scan.jsonl"))
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per mutant")
    ap.add_argument("--only", nargs="*", default=None, help="scan only these mutant names (e.g. survivors)")
    args = ap.parse_args()
    if args.generate:
        generate()
        return
    out = args.out.resolve()
    tests = [str((ROOT / t).resolve().relative_to(ROOT)) for t in args.tests]
    os.chdir(MUTANTS)  # the copy: its msmem_core and plugins come first on sys.path (tests/conftest.py)
    for path in (MUTANTS / "simulators", MUTANTS / "plugins", MUTANTS):
        sys.path.insert(0, str(path))
    names = mutant_names(args.module)
    if args.only is not None:
        names = [n for n in names if n in set(args.only)]
    seen = {}
    if out.exists():
        seen = {r["mutant"]: r for r in map(json.loads, out.read_text().splitlines()) if r}
    # numba's OpenMP layer does not survive fork (the child dies with SIGTERM, as in mutmut's fork
    # server); its workqueue layer does
    os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
    import pytest

    # warm up once here, unmutated: imports, numba kernels (loaded from numba's cache), the test modules;
    # every child inherits them (ig.py holds no cache that would carry an unmutated result over)
    with open(os.devnull, "w") as null:
        saved = os.dup(1), os.dup(2)
        os.dup2(null.fileno(), 1)
        os.dup2(null.fileno(), 2)
        try:
            pytest.main(["-q", "-p", "no:cacheprovider", *tests])
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)

    if run_child("", tests, args.timeout) != "survived":
        sys.exit("the tests fail without a mutant: fix them before scanning")
    if run_child("fail", tests, args.timeout) != "killed":
        sys.exit("the tests pass with mutmut's programmatic failure: they do not reach the mutated module")
    todo = [n for n in names if n not in seen]
    print(f"{args.module}: {len(names)} mutants, {len(names) - len(todo)} already scanned, tests {' '.join(tests)}")
    with out.open("a") as f:
        for i, name in enumerate(todo, 1):
            t0 = time.monotonic()
            status = run_child(name, tests, args.timeout)
            rec = {"mutant": name, "status": status, "seconds": round(time.monotonic() - t0, 2)}
            seen[name] = rec
            f.write(json.dumps(rec) + "\n")
            f.flush()
            print(f"[{i}/{len(todo)}] {status:8s} {name}", flush=True)
    counts = Counter(seen[n]["status"] for n in names)
    killed = counts["killed"] + counts["timeout"]
    print(f"{args.module}: {killed} of {len(names)} killed ({100 * killed / max(len(names), 1):.0f} %): {dict(counts)}")


if __name__ == "__main__":
    main()
