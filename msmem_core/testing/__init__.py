"""Testing kit for msmem and its plugins.

- ``msmem_core.testing.fixtures`` (auto-loaded as a pytest plugin): ``plugin_manager`` (a fresh,
  fully loaded manager per test), ``bare_plugin_manager`` (nothing loaded) and ``fake_simulator``.
- ``FakeSimulator``: a tiny in-memory backend for unit tests of loops, never for a feature.
- ``msmem_core.testing.conformance.simulator_conformance(factory)``: the suite a backend runs to
  prove it implements the Simulator vocabulary and its conventions.
"""

from msmem_core.testing.fake import FakeSimulator

__all__ = ["FakeSimulator"]
