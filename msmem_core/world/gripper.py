"""The parallel-jaw gripper every backend builds and every skill plans with."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from msmem_core.util.validation import FROZEN_MODEL_CONFIG

HandDims = tuple[float, float, float] | tuple[float, float, float, float, float]
"""(width along the closing axis, thickness, depth along the approach) of a hand behind the fingers,
optionally followed by (width, length) of the arm's wrist behind the hand, on the approach axis."""


class GripperSpec(BaseModel):
    """Floating parallel-jaw gripper.

    Gripper frame: origin at the centre between the fingertip pads; x = closing direction (the
    grasp baseline b), z = approach direction a, y = z cross x. Fingers are boxes centred at
    x = +-(opening/2 + finger_thickness/2), spanning z in [-finger_length, 0]; the palm is a box
    behind them, spanning z in [-finger_length - palm_depth, -finger_length].
    """

    model_config = FROZEN_MODEL_CONFIG

    max_opening_m: float = Field(0.08, gt=0.0, le=0.3)
    finger_length_m: float = Field(0.05, gt=0.0)
    finger_thickness_m: float = Field(0.01, gt=0.0)
    finger_width_m: float = Field(0.02, gt=0.0)
    palm_depth_m: float = Field(0.03, gt=0.0)
    palm_width_m: float = Field(0.02, gt=0.0)
    finger_friction: float = Field(1.0, ge=0.0)
    mass_kg: float = Field(0.5, gt=0.0)
    finger_force_n: float = Field(40.0, gt=0.0)

    @property
    def palm_length_m(self) -> float:
        """Extent of the palm along x: it spans both fully opened fingers."""
        return self.max_opening_m + 2 * self.finger_thickness_m

    def boxes(self, opening_m: float) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """(centre, half-extents) of the left finger, right finger and palm in the gripper frame."""
        fz = -self.finger_length_m / 2
        fx = opening_m / 2 + self.finger_thickness_m / 2
        finger_half = np.array([self.finger_thickness_m / 2, self.finger_width_m / 2, self.finger_length_m / 2])
        palm_half = np.array([self.palm_length_m / 2, self.palm_width_m / 2, self.palm_depth_m / 2])
        palm_c = np.array([0.0, 0.0, -self.finger_length_m - self.palm_depth_m / 2])
        return [
            (np.array([-fx, 0.0, fz]), finger_half),
            (np.array([fx, 0.0, fz]), finger_half),
            (palm_c, palm_half),
        ]
