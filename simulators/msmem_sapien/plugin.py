"""Registers ``sapien`` whether or not the library is installed (habitat-lab's pattern)."""

import warnings
from collections.abc import Callable, Iterable
from typing import Any

from msmem_core.plugins import SimulatorSpec, hookimpl, missing_extra_factory
from msmem_sapien.config import SapienConfig


def _factory() -> Callable[[Any], Any]:
    """``SapienSimulator`` when sapien imports; else a factory whose call says which extra to install."""
    try:
        with warnings.catch_warnings():  # "Failed to find system libvulkan": it then uses its bundled loader
            warnings.simplefilter("ignore", UserWarning)
            import sapien  # noqa: F401
    except ImportError as e:
        return missing_extra_factory("simulator", "sapien", "sapien", e)
    from msmem_sapien.simulator import SapienSimulator  # a failure here is a bug, reported as a broken plugin

    return SapienSimulator


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(
        name="sapien",
        factory=_factory(),
        config_model=SapienConfig,
        description="SAPIEN 3 on PhysX CPU; SAPIEN's renderer when a Vulkan device works, else ray casting "
        "(optional extra: pip install 'msmem[sapien]')",
        extra="sapien",
    )
