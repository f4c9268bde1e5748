"""Objective term ``travel-cost``: minus the seconds an action would take.

``seconds = seconds_per_kind[kind]`` (a fixed time per action kind, ``default_seconds`` for kinds not
listed), plus for a view the camera's travel from the previous viewpoint at ``camera_speed_mps``,
plus for a manipulation with ``start_m`` and ``length_m`` (pushes, nudges) the tool's path
(in from the shelf front to the start, the move, and back) at ``gripper_speed_mps``.

Terms see one decision at a time, not the history, so the previous viewpoint is inferred from
``ctx.visited`` (the views visited since the last manipulation): the view that appeared since the
last call. After a manipulation the camera has not moved, so the last known viewpoint is kept.
Weighted in config, e.g. ``{name: travel-cost, weight: 5.0}`` trades 5 nats of information gain
for one second.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import CandidateBatch, DecisionContext, Term

FRONT_M = (0.0, -0.1)
"""Where the gripper enters the shelf (x, y), for the path estimate."""


class TravelCostConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    seconds_per_kind: dict[str, float] = Field(
        default_factory=lambda: {"view": 1.0, "push": 10.0, "grasp": 15.0, "nudge": 8.0})
    """Fixed time per action kind (camera settling, approach and retreat, ...)."""
    default_seconds: float = Field(5.0, ge=0.0)
    """Time of an action kind not in ``seconds_per_kind``."""
    camera_speed_mps: float = Field(0.25, gt=0.0)
    gripper_speed_mps: float = Field(0.1, gt=0.0)


class TravelCost(Term):
    """Applies to every category; returns -seconds."""

    def __init__(self, config: TravelCostConfig | None = None) -> None:
        self.config = config or TravelCostConfig()
        self._seen: set[int] = set()
        self._last_view: int | None = None

    def _track(self, visited: set[int]) -> None:
        new = set(visited) - self._seen
        if new:
            self._last_view = max(new)
        self._seen = set(visited)

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]:
        cfg = self.config
        self._track(ctx.visited)
        kinds = [a.kind for a in batch.actions]
        seconds = np.array([cfg.seconds_per_kind.get(k, cfg.default_seconds) for k in kinds], dtype=np.float64)
        if batch.category == "perception" and batch.view_indices is not None and self._last_view is not None:
            pos = ctx.viewpoints[:, :3, 3]
            seconds += np.linalg.norm(pos[batch.view_indices] - pos[self._last_view], axis=1) / cfg.camera_speed_mps
        elif batch.category == "manipulation":
            for i, a in enumerate(batch.actions):
                start, length = getattr(a, "start_m", None), getattr(a, "length_m", None)
                if start is not None and length is not None:
                    reach = float(np.hypot(start[0] - FRONT_M[0], start[1] - FRONT_M[1]))
                    seconds[i] += (2 * reach + float(length)) / cfg.gripper_speed_mps
        return -seconds
