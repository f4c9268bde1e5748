"""Hold an msmem output-folder lock from another process, for the lock tests.

``python tests/support/hold_lock.py FOLDER [--run] [--seconds S] [--die]``: takes the lock of FOLDER (a
bench or datagen folder; ``--run``: the lock of a ``msmem run`` folder), prints ``locked`` and holds it
for S seconds (default 120) or until it receives ``SIGUSR1`` (then it releases the lock and ends normally),
or with ``--die`` kills itself at once without releasing it (as ``kill -9`` would), leaving a lock file
that names a dead process.
"""

from __future__ import annotations

import argparse
import os
import signal
import time
from pathlib import Path

from msmem_core.run.lock import folder_lock, run_lock_file

parser = argparse.ArgumentParser()
parser.add_argument("folder", type=Path)
parser.add_argument("--run", action="store_true")
parser.add_argument("--seconds", type=float, default=120.0)
parser.add_argument("--die", action="store_true")
args = parser.parse_args()


def _release(signum: int, frame: object) -> None:
    raise SystemExit(0)


signal.signal(signal.SIGUSR1, _release)
with folder_lock(args.folder, run_lock_file(args.folder) if args.run else None):
    print("locked", flush=True)
    if args.die:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(args.seconds)
