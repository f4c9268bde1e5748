"""A simulator backend by name, through the plugin manager: code outside the backends never imports one.

``msmem run`` builds its simulator from ``RunConfig.simulator`` (``msmem_core.run.runner.build_episode``);
data generation, evaluation and benchmarks that drive a simulator themselves take a ``ComponentRef``
(``--sim NAME`` on the command line) and call :func:`build_simulator`.
"""

from __future__ import annotations

from typing import Any

from msmem_core.interfaces import Simulator
from msmem_core.plugins.manager import ComponentRef, MsmemPluginManager, get_plugin_manager


def build_simulator(ref: ComponentRef | str, pm: MsmemPluginManager | None = None, **common: Any) -> Simulator:
    """The backend ``ref`` names (``"pybullet"``, ``ComponentRef(name="sapien", params={...})``).

    ``common`` supplies values (``seed``, ``camera``, ``label_noise``, ...) for the fields of the
    backend's config model that ``ref.params`` leaves unset; fields the backend does not have are
    ignored. An unknown name, bad params or a missing optional dependency raise a ``PluginError``
    naming the simulator.
    """
    sim: Simulator = (pm or get_plugin_manager()).build("simulator", ref, where="simulator", **common)
    return sim


def check_simulator(ref: ComponentRef | str, pm: MsmemPluginManager | None = None, **common: Any) -> None:
    """Build the backend once and close it: a bad ``--sim`` fails in one line before any worker starts."""
    build_simulator(ref, pm, **common).close()
