from collections.abc import Iterable

from msmem_core.plugins import SimulatorSpec, hookimpl
from msmem_core.util.quiet import quiet_stdio

with quiet_stdio():  # pybullet prints its build time on import
    from msmem_pybullet.simulator import PyBulletConfig, PyBulletSimulator


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(
        name="pybullet",
        factory=PyBulletSimulator,
        config_model=PyBulletConfig,
        description="PyBullet (DIRECT mode, TinyRenderer depth and segmentation)",
    )
