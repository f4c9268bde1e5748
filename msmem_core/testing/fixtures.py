"""pytest fixtures, auto-loaded through the ``pytest11`` entry point of the msmem distribution."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from msmem_core.plugins.manager import MsmemPluginManager, get_plugin_manager
from msmem_core.testing.fake import FakeSimulator


@pytest.fixture
def plugin_manager() -> Iterator[MsmemPluginManager]:
    """A fresh manager with every installed plugin loaded (plus ``MSMEM_PLUGINS``)."""
    yield get_plugin_manager()


@pytest.fixture
def bare_plugin_manager() -> Iterator[MsmemPluginManager]:
    """A fresh manager with nothing loaded: register what the test needs."""
    yield MsmemPluginManager()


@pytest.fixture
def fake_simulator() -> FakeSimulator:
    return FakeSimulator()
