"""Thread settings (``msmem_core.util.threads``): importing msmem_core changes nothing; ``configure_threads``
sets the OpenMP variables unless set (and numba's config when numba is imported already); the ``msmem``
command, ``build_episode`` and the executors' worker processes apply them. Each case runs in a fresh
Python whose environment lacks the variables."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from msmem_core.util.threads import THREAD_ENV

ROOT = Path(__file__).resolve().parents[1]


def run_python(code: str, **env: str) -> dict[str, str | None]:
    """Run ``code`` in a fresh interpreter (environment without the thread variables, plus ``env``);
    the code prints one JSON object as its last line."""
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_ENV}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False,
                         env={**clean, **env}, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


ENV = "import json, os; print(json.dumps({k: os.environ.get(k) for k in ('NUMBA_THREADING_LAYER', 'OMP_WAIT_POLICY')}))"


def test_importing_msmem_core_sets_no_environment() -> None:
    out = run_python("import msmem_core, msmem_core.run.runner, msmem_core.plugins\n" + ENV)
    assert out == {"NUMBA_THREADING_LAYER": None, "OMP_WAIT_POLICY": None}


def test_configure_threads_sets_the_defaults_and_keeps_what_is_set() -> None:
    code = "from msmem_core.util.threads import configure_threads; configure_threads()\n" + ENV
    assert run_python(code) == THREAD_ENV
    assert run_python(code, OMP_WAIT_POLICY="ACTIVE") == {**THREAD_ENV, "OMP_WAIT_POLICY": "ACTIVE"}


def test_configure_threads_updates_numba_imported_before_it() -> None:
    code = ("import json, numba\nbefore = numba.config.THREADING_LAYER\n"
            "from msmem_core.util.threads import configure_threads; configure_threads()\n"
            "print(json.dumps({'before': before, 'after': numba.config.THREADING_LAYER}))")
    assert run_python(code) == {"before": "default", "after": "omp"}


def test_the_msmem_command_configures_threads_before_running_a_command() -> None:
    code = ("import sys; sys.argv = ['msmem', '--help']\nfrom msmem_core.cli import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n" + ENV)
    assert run_python(code) == THREAD_ENV


def test_build_episode_configures_threads_before_loading_the_plugins() -> None:
    code = ("import sys\nfrom msmem_core.run import runner\n"
            "def stop(*a, **k):\n    import json, os\n"
            "    print(json.dumps({'torch': 'torch' in sys.modules, 'policy': os.environ.get('OMP_WAIT_POLICY')}))\n"
            "    raise SystemExit(0)\n"
            "runner.MsmemPluginManager.build = stop\n"
            "from msmem_core.config import RunConfig\nfrom msmem_core.plugins import get_plugin_manager\n"
            "runner.build_episode(RunConfig(), get_plugin_manager())\n")
    assert run_python(code) == {"torch": False, "policy": "PASSIVE"}


@pytest.mark.parametrize("threads", [1, None])
def test_executor_workers_configure_threads(threads: int | None) -> None:
    code = ("import json, os\nfrom msmem_core.run.executors import run_tasks\n"
            f"out = run_tasks(os.getenv, ['OMP_WAIT_POLICY', 'NUMBA_THREADING_LAYER'], workers=2, progress=False, "
            f"threads={threads})\n"
            "print(json.dumps({'parent': os.environ.get('OMP_WAIT_POLICY'), 'workers': out}))")
    assert run_python(code) == {"parent": None, "workers": ["PASSIVE", "omp"]}
