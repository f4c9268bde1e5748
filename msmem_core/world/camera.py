"""Camera model and the Observation record every simulator backend returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field, model_validator

from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Int


class CameraConfig(BaseModel):
    """Pinhole depth + semantics camera (MEM's: 640x480, 58 deg vertical FOV)."""

    model_config = FROZEN_MODEL_CONFIG

    width_px: Int = Field(640, ge=8, le=4096)
    height_px: Int = Field(480, ge=8, le=4096)
    vfov_deg: float = Field(58.0, gt=1.0, lt=170.0)
    near_m: float = Field(0.07, gt=0.0)
    far_m: float = Field(1.5, gt=0.0)

    @model_validator(mode="after")
    def _near_before_far(self) -> CameraConfig:
        if self.near_m >= self.far_m:
            raise ValueError(f"near_m ({self.near_m}) must be less than far_m ({self.far_m})")
        return self

    @property
    def fy(self) -> float:
        return 0.5 * self.height_px / np.tan(np.radians(self.vfov_deg) / 2)

    @property
    def intrinsics(self) -> NDArray[np.float64]:
        """3x3 K with square pixels and the principal point at the image centre."""
        f = self.fy
        return np.array([[f, 0.0, self.width_px / 2], [0.0, f, self.height_px / 2], [0.0, 0.0, 1.0]])

    def pixel_rays(self, stride: int = 1) -> NDArray[np.float64]:
        """Camera-frame directions (H', W', 3) with z = 1 through the centres of every stride-th pixel."""
        k = self.intrinsics
        u = np.arange(stride / 2, self.width_px, stride)
        v = np.arange(stride / 2, self.height_px, stride)
        uu, vv = np.meshgrid(u, v)
        return np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], axis=-1)


@dataclass
class Observation:
    """One camera frame.

    Conventions: ``depth`` is z-depth in metres along the optical axis (0 where nothing was hit
    before ``far``); the camera frame is OpenCV's (x right, y down, z forward); ``camera_to_world``
    maps camera-frame points into the world; ``labels`` holds a semantic class id per pixel
    (0 = background: shelf or nothing), possibly corrupted by the backend's segmentation noise.
    """

    depth: NDArray[np.float32]
    labels: NDArray[np.int16]
    intrinsics: NDArray[np.float64]
    camera_to_world: NDArray[np.float64]
    object_ids: NDArray[np.int32] | None = None
    """Ground-truth object id per pixel (-1 none); for tests and metrics, never for the belief."""
    meta: dict[str, object] = field(default_factory=dict)

    def points_world(self) -> NDArray[np.float64]:
        """World coordinates (N, 3) of every pixel with a depth return."""
        v, u = np.nonzero(self.depth > 0)
        z = self.depth[v, u].astype(np.float64)
        k = self.intrinsics
        pc = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0] * z, (v + 0.5 - k[1, 2]) / k[1, 1] * z, z], axis=-1)
        return pc @ self.camera_to_world[:3, :3].T + self.camera_to_world[:3, 3]
