"""The testing kit's ``FakeSimulator`` registered as a simulator plugin named ``fake``.

Used by docs/how-to/write-a-simulator.md to show registration without installing anything::

    PYTHONPATH=examples MSMEM_PLUGINS=fake=fake_backend msmem plugins

It renders only the shelf's back wall, so it fails the conformance suite, as it should.
"""

from collections.abc import Iterable

from pydantic import BaseModel, ConfigDict

from msmem_core.plugins import SimulatorSpec, hookimpl
from msmem_core.testing import FakeSimulator
from msmem_core.world.camera import CameraConfig


class FakeConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig()
    """The run's camera (filled in by the runner when unset)."""


def make_fake(config: FakeConfig) -> FakeSimulator:
    return FakeSimulator(config.camera)


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(name="fake", factory=make_fake, config_model=FakeConfig,
                        description="Back wall only, objects invisible (unit tests of loops)")
