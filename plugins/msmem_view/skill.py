"""Next-best-view skill: proposes every viewpoint not visited since the last manipulation that the run's
robot reaches (its wrist camera, collision-free; every viewpoint without an arm)."""

from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import Action, Category, DecisionContext, Outcome, PerceptionAction, Simulator, Skill


class ViewAction(PerceptionAction):
    """Observe from viewpoint ``view`` (an index into the run's viewpoints)."""

    kind: str = "view"


class ViewConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ViewSkill(Skill):
    category: ClassVar[Category] = "perception"

    def __init__(self, config: ViewConfig | None = None) -> None:
        self.config = config or ViewConfig()

    def propose(self, ctx: DecisionContext) -> list[Action]:
        robot = ctx.workspace.robot
        reach = None if robot is None else robot.reachable_views(ctx.viewpoints, ctx.shelf)  # cached by the robot
        return [ViewAction(view=v) for v in range(len(ctx.viewpoints))
                if v not in ctx.visited and (reach is None or reach[v])]

    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        assert isinstance(action, ViewAction)
        obs = sim.observe(ctx.viewpoints[action.view])
        return Outcome(success=True, observation=obs, info={"view": action.view})
