"""Registers ``sapien`` whether or not the library is installed (habitat-lab's pattern)."""

from collections.abc import Callable, Iterable
from typing import Any

from msmem_core.errors import PluginError
from msmem_core.plugins import SimulatorSpec, hookimpl, missing_extra_factory
from msmem_sapien.config import SapienConfig


def _factory() -> Callable[[Any], Any]:
    try:
        import sapien  # noqa: F401
    except ImportError as e:
        return missing_extra_factory("simulator", "sapien", "sapien", e)

    def not_yet(_config: Any) -> Any:
        raise PluginError("simulator 'sapien': the SAPIEN backend is not implemented yet (tracked in issue 7)")

    return not_yet


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(
        name="sapien",
        factory=_factory(),
        config_model=SapienConfig,
        description="SAPIEN 3 on PhysX CPU (optional extra: pip install 'msmem[sapien]')",
        extra="sapien",
    )
