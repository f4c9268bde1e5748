"""pytest fixtures, auto-loaded through the ``pytest11`` entry point of the msmem distribution."""

from __future__ import annotations

import pytest

from msmem_core.plugins.manager import MsmemPluginManager, get_plugin_manager
from msmem_core.testing.fake import FakeSimulator


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
