"""pytest fixtures, auto-loaded through the ``pytest11`` entry point of the msmem distribution."""

from __future__ import annotations

import pytest

from msmem_core.plugins.manager import MsmemPluginManager, get_plugin_manager
from msmem_core.testing.fake import FakeSimulator
from msmem_core.util.threads import configure_threads


def pytest_configure(config: pytest.Config) -> None:
    """Thread settings for test sessions that run episodes, before test modules import torch or numba."""
    configure_threads()


@pytest.fixture
def plugin_manager() -> MsmemPluginManager:
    """A fresh manager with every installed plugin loaded (plus ``MSMEM_PLUGINS``)."""
    return get_plugin_manager()


@pytest.fixture
def bare_plugin_manager() -> MsmemPluginManager:
    """A fresh manager with nothing loaded: register what the test needs."""
    return MsmemPluginManager()


@pytest.fixture
def fake_simulator() -> FakeSimulator:
    return FakeSimulator()
