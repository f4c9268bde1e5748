import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# This checkout's packages before the installed ones: ROOT so MSMEM_PLUGINS can name tests.support.*
# modules, and the plugin folders so that a copy of the project (mutmut's mutants/) tests its own,
# mutated plugins rather than the editable install's.
for _path in (ROOT / "simulators", ROOT / "plugins", ROOT):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from msmem_core.util.threads import configure_threads  # noqa: E402

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
configure_threads()  # before any test module imports torch or numba


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """One torch thread for a test module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``),
    its module-scoped fixtures included; the previous count is restored after the module."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


UNIT_MODULES = frozenset({
    "test_architecture", "test_backbone", "test_belief", "test_ceiling", "test_class_map",
    "test_cnabu_loss_mutation", "test_config", "test_conformance", "test_doig", "test_fpp", "test_funnel",
    "test_docs_imports", "test_fusion", "test_fusion_mutation", "test_geometry", "test_grasp_exit", "test_grasp_losses",
    "test_grasp_losses_mutation", "test_groundtruth", "test_ig", "test_ig_gain", "test_ig_incremental",
    "test_ig_information", "test_ig_mutation", "test_malloc", "test_mesh_objects", "test_metrics",
    "test_metrics_mutation", "test_msas_loop", "test_no_history_words", "test_object_counts",
    "test_plugin_classes", "test_plugin_isolation", "test_pybullet_sim", "test_reach_filter",
    "test_robot_conformance", "test_runfolder", "test_scene_classes", "test_tiers", "test_tracking", "test_vmf",
})
"""The fast tier (``make test-unit``, marker ``unit``): the modules whose tests took at most about 10 s
in all on a loaded 2-core machine (pytest's junit times of a full ``make test``): the math, the core's
loop and data types, one-component physics. Episodes, training, CLI runs and the docs are left out."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in UNIT_MODULES:
            item.add_marker(pytest.mark.unit)
