import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from msmem_core.util.threads import configure_threads

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # so MSMEM_PLUGINS can name tests.support.* modules
    sys.path.insert(0, str(ROOT))
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
