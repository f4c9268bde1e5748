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
