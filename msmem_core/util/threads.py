"""How the OpenMP runtimes of torch and numba behave in a process that runs episodes.

``configure_threads()`` sets these environment variables, unless they are set already:

- ``NUMBA_THREADING_LAYER=omp``: numba probes TBB first and warns when the installed one is too old;
  OpenMP is the layer msmem uses.
- ``OMP_WAIT_POLICY=PASSIVE``: OpenMP worker threads (torch's and numba's) sleep at barriers instead of
  spinning. A spinning thread takes its core from the threads still working whenever the machine has
  more runnable threads than cores (two episodes in parallel, or other jobs); see docs/explanation/performance.md,
  "Thread settings".

An OpenMP runtime reads its environment once, when it loads: with ``import torch``, or at numba's first
parallel kernel. So the call must come before that in every process that runs episodes. The ``msmem``
command calls it first thing; ``build_episode`` and ``set_threads`` of the runner call it (for library
use; ``build_episode`` loads the plugins, which import torch); the executors' worker processes call it
before they run a task (Ray tasks get the variables through their runtime environment); msmem's pytest
plugin (``msmem_core.testing.fixtures``) and the test suite's ``conftest.py`` call it. Child processes
inherit the environment. The call is idempotent and
cheap; calling it again later changes nothing in runtimes already loaded.

Thread *counts* are per episode: ``msmem_core.run.runner.set_threads`` and
``msmem_core.run.executors.limit_threads``.
"""

from __future__ import annotations

import os
import sys

THREAD_ENV: dict[str, str] = {"NUMBA_THREADING_LAYER": "omp", "OMP_WAIT_POLICY": "PASSIVE"}
"""The variables ``configure_threads`` sets, with the values it sets when they are unset."""


def configure_threads() -> dict[str, str]:
    """Set the ``THREAD_ENV`` variables that are unset; returns their values in effect.

    numba reads ``NUMBA_THREADING_LAYER`` into its config when it is imported, so when numba is already
    imported its config is updated too (it takes effect unless a parallel kernel has run already).
    """
    for name, value in THREAD_ENV.items():
        os.environ.setdefault(name, value)
    numba = sys.modules.get("numba")
    if numba is not None and hasattr(numba, "config"):
        numba.config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]
    return {name: os.environ[name] for name in THREAD_ENV}
