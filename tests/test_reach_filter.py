"""``msmem_core.msas.ReachFilter``: which of one skill's candidates the run's robot can follow, checked one
at a time, with the belief's obstacles given to the robot once per decision."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from msmem_robots.floating import FloatingRobot
from numpy.typing import NDArray

from msmem_core.interfaces import (
    Action,
    Category,
    DecisionContext,
    Outcome,
    PerceptionAction,
    Reach,
    Simulator,
    Skill,
    Workspace,
)
from msmem_core.msas import BeliefObstacles, BoundSkill, ReachFilter
from msmem_core.testing.builders import belief_with_boxes, decision_context, default_workspace
from msmem_core.world.scene import ShelfSpec


class Poke(Action):
    kind: str = "poke"
    category: Category = "manipulation"
    x_m: float | None = None
    """Where the tool goes; None: the action has no tool path."""


class PokeSkill(Skill):
    category: ClassVar[Category] = "manipulation"

    def propose(self, ctx: DecisionContext) -> list[Action]:
        return []

    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        return Outcome()

    def tool_path(self, action: Action, workspace: Workspace) -> NDArray[np.float64] | None:
        assert isinstance(action, Poke)
        if action.x_m is None:
            return None
        poses = np.stack([np.eye(4), np.eye(4)])
        poses[:, 0, 3] = action.x_m
        return poses


class Look(Skill):
    def propose(self, ctx: DecisionContext) -> list[Action]:
        return [PerceptionAction(kind="look", view=0)]

    def execute(self, sim: Simulator, action: Action, ctx: DecisionContext) -> Outcome:
        return Outcome()


class LeftArm(FloatingRobot):
    """An arm that follows tool paths at x < 0 only, recording the obstacles it is given."""

    arm = True

    def __init__(self) -> None:
        super().__init__()
        self.obstacles: list[NDArray[np.float64] | None] = []

    def use_obstacles(self, boxes: NDArray[np.float64] | None) -> None:
        self.obstacles.append(boxes)

    def reach_path(self, tool_poses: NDArray[np.float64], shelf: ShelfSpec, step_m: float = 0.02) -> Reach:
        return Reach(bool(tool_poses[-1][0, 3] < 0), ())


def _ctx(robot: FloatingRobot | None) -> DecisionContext:
    ws = default_workspace()
    belief = belief_with_boxes(ws.grid, [((-0.1, 0.1, 0.0), (0.1, 0.2, 0.1), 1)], free="none")
    return decision_context(belief, workspace=Workspace(ws.grid, ws.shelf, ws.gripper, ws.num_classes, robot))


def test_candidates_are_checked_only_with_an_arm_and_only_for_manipulation_skills() -> None:
    pokes: list[Action] = [Poke(x_m=-0.1)]
    poke, look = BoundSkill("poke", PokeSkill()), BoundSkill("look", Look())
    for robot in (None, FloatingRobot()):
        ctx = _ctx(robot)
        assert ReachFilter.of(poke, pokes, ctx, BeliefObstacles(ctx)) is None
    ctx = _ctx(LeftArm())
    assert ReachFilter.of(look, look.skill.propose(ctx), ctx, BeliefObstacles(ctx)) is None
    assert ReachFilter.of(poke, pokes, ctx, BeliefObstacles(ctx)) is not None


def test_the_filter_counts_what_it_checked_and_refused_and_gives_the_obstacles_once_per_decision() -> None:
    robot = LeftArm()
    ctx = _ctx(robot)
    obstacles = BeliefObstacles(ctx)
    a = ReachFilter.of(BoundSkill("poke", PokeSkill()), [Poke(x_m=-0.1), Poke(x_m=0.2), Poke()], ctx, obstacles)
    b = ReachFilter.of(BoundSkill("prod", PokeSkill()), [Poke(x_m=0.3)], ctx, obstacles)
    assert a is not None
    assert b is not None
    assert robot.obstacles == []  # nothing before the first check
    assert [a.admissible(i) for i in (1, 0, 2)] == [False, True, True]  # no tool path: nothing to follow
    assert (a.checked, a.unreachable) == (3, 1)
    assert b.admissible(0) is False
    assert (b.checked, b.unreachable) == (1, 1)
    assert len(robot.obstacles) == 1  # one set-up for the decision, shared by its skills
    boxes = robot.obstacles[0]
    assert boxes is not None
    assert len(boxes) > 0
    np.testing.assert_array_equal(boxes, ctx.grid.column_boxes(ctx.belief.expected_occupancy() > 0.5))
