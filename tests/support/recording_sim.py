"""A simulator plugin ``recording``: the testing kit's ``FakeSimulator`` that appends the config it was
built with to the JSON-lines file named by ``MSMEM_TEST_SIM_LOG`` (across worker processes), so
tests can check that ``--sim`` reaches the code that builds a simulator."""

import json
import os
from collections.abc import Iterable
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from msmem_core.plugins import SimulatorSpec, hookimpl
from msmem_core.testing import FakeSimulator
from msmem_core.world.camera import CameraConfig


class RecordingConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig(width_px=64, height_px=48)
    seed: int = 0
    label_noise: float = Field(0.05, ge=0.0, le=1.0)


def make_recording(config: RecordingConfig) -> FakeSimulator:
    log = os.environ.get("MSMEM_TEST_SIM_LOG")
    if log:
        with open(log, "a") as f:
            f.write(config.model_dump_json() + "\n")
    return FakeSimulator(config.camera)


def built(log: str) -> list[dict[str, object]]:
    """The configs the simulator was built with, in order."""
    path = Path(log)
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(name="recording", factory=make_recording, config_model=RecordingConfig,
                        description="FakeSimulator that records how it was built (tests)")
