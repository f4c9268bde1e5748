"""Config of the SAPIEN backend; importable without sapien so the backend always registers."""

from pydantic import BaseModel, ConfigDict

from msmem_core.camera import CameraConfig
from msmem_core.gripper import GripperSpec


class SapienConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig()
    gripper: GripperSpec = GripperSpec()
    label_noise: float = 0.05
    seed: int = 0
