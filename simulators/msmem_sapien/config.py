"""Config of the SAPIEN backend; importable without sapien so the backend always registers."""

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from msmem_core.world.camera import CameraConfig
from msmem_core.world.gripper import GripperSpec


class SapienConfig(BaseModel):
    """Configuration of the SAPIEN 3 backend (PhysX on the CPU)."""

    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig()
    gripper: GripperSpec = GripperSpec()
    label_noise: float = Field(0.05, ge=0.0, le=1.0)
    """Probability that, in one view, a visible object is labelled entirely as its confusable class."""
    seed: int = 0
    """Seed of every random choice of the backend (segmentation noise)."""
    time_step_s: float = Field(1.0 / 240.0, gt=0.0, le=0.05)
    settle_s: float = Field(1.0, ge=0.0)
    """Simulated time objects settle for after ``reset``."""
    renderer: Literal["auto", "native", "raycast"] = "auto"
    """Camera: ``native`` = SAPIEN's Vulkan renderer (needs a Vulkan device, e.g. lavapipe on the CPU),
    ``raycast`` = open3d ray casting over the collision geometry, ``auto`` = native when a device works."""
    solver_position_iterations: int = Field(50, ge=1, le=255)
    """PhysX position iterations of every body (its default, 10, lets squeezed light objects slip)."""
