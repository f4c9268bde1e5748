"""The fixed candidate viewpoints: three curved grids in front of the shelf (MEM's 300 views).

Each grid is a patch of a sphere of radius ``radius_m`` around one target point inside the shelf
(left, middle, right), spanning ``azimuth_deg`` around the shelf's outward normal (-y) and
``elevation_deg`` above the horizontal; every camera looks at its grid's target. View index
``g * grid**2 + i_el * grid + i_az`` (grid g in the order of ``targets_x_m``, elevation row, azimuth
column), so neighbouring indices are neighbouring cameras.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field, model_validator

from msmem_core.errors import UserError
from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Int
from msmem_core.world.geometry import look_at
from msmem_core.world.scene import ShelfSpec


class ViewpointConfig(BaseModel):
    """Where the candidate cameras are (defaults: 3 x 10 x 10 = 300 views, as MEM)."""

    model_config = FROZEN_MODEL_CONFIG

    targets_x_m: tuple[float, ...] = (-0.25, 0.0, 0.25)
    """x of each grid's target (left, middle, right); one 10x10 grid per target."""
    target_y_m: float = 0.19
    """Depth of the targets (about the middle of the shelf)."""
    target_z_m: float = 0.14
    """Height of the targets (about half the shelf height)."""
    radius_m: float = Field(0.55, gt=0.0)
    """Camera distance from its target."""
    azimuth_deg: tuple[float, float] = (-30.0, 30.0)
    """Azimuth range about -y (0 = straight in front of the target, positive = towards +x)."""
    elevation_deg: tuple[float, float] = (-10.0, 35.0)
    """Elevation range above the horizontal plane through the target."""
    grid: Int = Field(10, ge=1, le=100)
    """Views per grid side (grid x grid views per target)."""

    @model_validator(mode="after")
    def _ranges(self) -> ViewpointConfig:
        if not self.targets_x_m:
            raise ValueError("targets_x_m must name at least one target")
        for name in ("azimuth_deg", "elevation_deg"):
            lo, hi = getattr(self, name)
            if lo > hi or lo <= -90 or hi >= 90:
                raise ValueError(f"{name} must satisfy -90 < lower <= upper < 90, got ({lo}, {hi})")
        return self

    @property
    def num_views(self) -> int:
        return len(self.targets_x_m) * self.grid**2


def _angles(lo: float, hi: float, n: int) -> NDArray[np.float64]:
    return np.radians(np.linspace(lo, hi, n)) if n > 1 else np.radians(np.array([(lo + hi) / 2]))


def generate_viewpoints(cfg: ViewpointConfig, shelf: ShelfSpec | None = None) -> NDArray[np.float64]:
    """Camera-to-world poses ``[V, 4, 4]`` (OpenCV convention), ordered as the module docstring says.

    With ``shelf`` given, checks that every camera is in front of the shelf (y < 0), so no candidate
    view starts inside the shelf or behind its back board.
    """
    az = _angles(*cfg.azimuth_deg, cfg.grid)
    el = _angles(*cfg.elevation_deg, cfg.grid)
    ee, aa = np.meshgrid(el, az, indexing="ij")  # rows: elevation, columns: azimuth
    offsets = cfg.radius_m * np.stack([np.cos(ee) * np.sin(aa), -np.cos(ee) * np.cos(aa), np.sin(ee)], axis=-1).reshape(
        -1, 3
    )
    poses: list[NDArray[np.float64]] = []
    for tx in cfg.targets_x_m:
        target = np.array([tx, cfg.target_y_m, cfg.target_z_m])
        poses.extend(look_at(target + off, target) for off in offsets)
    out = np.stack(poses).astype(np.float64)
    if shelf is not None and np.any(out[:, 1, 3] >= 0.0):
        raise UserError(
            f"viewpoint config puts cameras inside or behind the shelf (max camera y = {out[:, 1, 3].max():.3f} m;"
            " must be < 0, the open front): increase radius_m, narrow azimuth_deg/elevation_deg or lower target_y_m"
        )
    return out


def default_start_view(cfg: ViewpointConfig) -> int:
    """Index of the first view of an episode: the centre of the middle grid (slightly above the target)."""
    g = len(cfg.targets_x_m) // 2
    return g * cfg.grid**2 + (cfg.grid // 2) * cfg.grid + cfg.grid // 2
