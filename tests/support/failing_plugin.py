"""Components that fail on purpose, for the fault tests: register with
``MSMEM_PLUGINS="failing=tests.support.failing_plugin"`` (spawned bench workers inherit it).

- skill ``flaky-view``: the view skill, raising ``RuntimeError`` from a helper function when asked to
  propose for the ``fail_at``-th time (0: the first step), or ``ValueError`` when built (``fail_build``);
- simulator ``dying-pybullet``: PyBullet, whose process kills itself (``SIGKILL``, as the out-of-memory
  killer would) when it is reset to a scene named in ``die_on``.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterable
from typing import Any

from msmem_pybullet.simulator import PyBulletConfig, PyBulletSimulator
from msmem_view.skill import ViewConfig, ViewSkill

from msmem_core.plugins import SimulatorSpec, SkillSpec, hookimpl


class FlakyViewConfig(ViewConfig):
    fail_at: int = 0
    """The call of ``propose`` (counted from 0: the step) that raises."""
    fail_build: bool = False
    """Raise when built."""


def _explode(call: int) -> None:
    raise RuntimeError(f"flaky on purpose at call {call}")


class FlakyView(ViewSkill):
    def __init__(self, config: FlakyViewConfig) -> None:
        if config.fail_build:
            raise ValueError("cannot build on purpose")
        super().__init__(ViewConfig(**config.model_dump(exclude={"fail_at", "fail_build"})))
        self.fail_at = config.fail_at
        self.calls = 0

    def propose(self, ctx: Any) -> list[Any]:
        if self.calls == self.fail_at:
            _explode(self.calls)  # raised in a function, not the method: the skill is still the one named
        self.calls += 1
        return super().propose(ctx)


class DyingConfig(PyBulletConfig):
    die_on: tuple[str, ...] = ()
    """Scene names whose reset kills this process."""


class DyingSimulator(PyBulletSimulator):
    def __init__(self, config: DyingConfig) -> None:
        super().__init__(PyBulletConfig(**config.model_dump(exclude={"die_on"})))
        self.die_on = set(config.die_on)

    def reset(self, scene: Any) -> None:
        if scene.name in self.die_on:
            os.kill(os.getpid(), signal.SIGKILL)
        super().reset(scene)


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(name="flaky-view", factory=FlakyView, config_model=FlakyViewConfig,
                    description="The view skill, failing on purpose at one step")


@hookimpl
def msmem_simulators() -> Iterable[SimulatorSpec]:
    yield SimulatorSpec(name="dying-pybullet", factory=DyingSimulator, config_model=DyingConfig,
                        description="PyBullet, killing its process on purpose at the reset of some scenes")
