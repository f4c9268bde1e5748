"""The fixed candidate viewpoints: three curved grids in front of the shelf (MEM's 300 views), or the
camera poses of a file (``poses_file``).

Each grid is a patch of a sphere of radius ``radius_m`` around one target point inside the shelf
(left, middle, right), spanning ``azimuth_deg`` around the shelf's outward normal (-y) and
``elevation_deg`` above the horizontal; every camera looks at its grid's target. View index
``g * grid**2 + i_el * grid + i_az`` (grid g in the order of ``targets_x_m``, elevation row, azimuth
column), so neighbouring indices are neighbouring cameras.

A poses file (docs/how-to/viewpoints.md) lists the views explicitly, as YAML or JSON::

    views:
      - {position_m: [-0.1, -0.5, 0.3], target_m: [0.0, 0.19, 0.14]}   # look-at (z up)
      - matrix: [[1, 0, 0, 0], [0, 0, 1, -0.5], [0, -1, 0, 0.2], [0, 0, 0, 1]]  # camera-to-world
    start_view: 0          # optional: the episode's first view
    front_views: [0, 1]    # optional: the grasp skill's virtual front cameras

or as a ``.npy`` array ``[V, 4, 4]`` of camera-to-world poses (OpenCV convention: x right, y down,
z forward). Views keep the file's order. Without ``start_view`` the episode starts from the most
frontal view nearest the shelf's centre line; without ``front_views`` the virtual front cameras are,
for the left, middle and right third of where the views look, the most frontal view of each.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import BaseModel, Field, field_validator, model_validator

from msmem_core.errors import UserError
from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Int, load_json, load_yaml
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
    poses_file: Path | None = None
    """A YAML, JSON or .npy file of camera poses used instead of the grids above (module docstring,
    docs/how-to/viewpoints.md); a relative path in a config file is relative to that file."""

    @field_validator("poses_file")
    @classmethod
    def _readable(cls, v: Path | None) -> Path | None:
        if v is not None:
            try:
                read_poses_file(v)
            except UserError as e:
                raise ValueError(str(e)) from None
        return v

    @model_validator(mode="after")
    def _ranges(self) -> ViewpointConfig:
        if self.poses_file is not None:
            fields = type(self).model_fields
            grids = sorted(k for k in fields if k != "poses_file" and getattr(self, k) != fields[k].default)
            if grids:
                raise ValueError(f"poses_file replaces the parametric grids: leave out {', '.join(grids)}")
            return self
        if not self.targets_x_m:
            raise ValueError("targets_x_m must name at least one target")
        for name in ("azimuth_deg", "elevation_deg"):
            lo, hi = getattr(self, name)
            if lo > hi or lo <= -90 or hi >= 90:
                raise ValueError(f"{name} must satisfy -90 < lower <= upper < 90, got ({lo}, {hi})")
        return self

    @property
    def num_views(self) -> int:
        if self.poses_file is not None:
            return len(read_poses_file(self.poses_file).poses)
        return len(self.targets_x_m) * self.grid**2


@dataclass(frozen=True)
class PoseFile:
    """A poses file, read and checked: the poses ``[V, 4, 4]``, its optional start and front views, and
    the SHA-256 of its bytes (benchmark fingerprints)."""

    poses: NDArray[np.float64]
    start_view: int | None
    front_views: tuple[int, ...] | None
    sha256: str


def read_poses_file(path: str | Path) -> PoseFile:
    """Read and check a poses file; ``UserError`` naming the file and the entry at fault. Cached per
    file content (path, size and modification time)."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise UserError(f"cannot read poses file {p}: {e.strerror or e}") from e
    return _read_poses(str(p.resolve()), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=8)
def _read_poses(path: str, size: int, mtime_ns: int) -> PoseFile:
    p = Path(path)
    raw = p.read_bytes()
    digest = hashlib.sha256(raw).hexdigest()
    where = f"poses file {p}"
    if p.suffix == ".npy":
        try:
            poses = np.load(p, allow_pickle=False)
        except ValueError as e:
            raise UserError(f"{where} is not a numpy array file: {e}") from e
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise UserError(f"{where} must hold an array [V, 4, 4] of camera-to-world poses, not {list(poses.shape)}")
        data: dict[str, Any] = {}
        poses = poses.astype(np.float64)
    else:
        try:
            data = load_json(raw.decode()) if p.suffix == ".json" else load_yaml(raw.decode())
        except (ValueError, UnicodeDecodeError, yaml.YAMLError) as e:
            raise UserError(f"{where} is not valid {'JSON' if p.suffix == '.json' else 'YAML'}: {e}") from e
        if not isinstance(data, dict) or not isinstance(data.get("views"), list):
            raise UserError(f"{where} must be a mapping with a list 'views' (or a .npy array [V, 4, 4])")
        extra = sorted(set(data) - {"views", "start_view", "front_views"})
        if extra:
            raise UserError(f"{where}: unknown key(s) {', '.join(extra)}; allowed: views, start_view, front_views")
        poses = np.stack([_pose_entry(entry, f"{where}: views.{i}") for i, entry in enumerate(data["views"])]) \
            if data["views"] else np.zeros((0, 4, 4))
    if len(poses) == 0:
        raise UserError(f"{where} lists no views")
    for i, t in enumerate(poses):
        _check_pose(t, f"{where}: views.{i}")
    n = len(poses)

    def index(v: Any, name: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < n:
            raise UserError(f"{where}: {name} must be a view index from 0 to {n - 1}, not {v!r}")
        return int(v)

    start = index(data["start_view"], "start_view") if data.get("start_view") is not None else None
    front = None
    if data.get("front_views") is not None:
        if not isinstance(data["front_views"], list) or not data["front_views"]:
            raise UserError(f"{where}: front_views must be a non-empty list of view indices")
        front = tuple(index(v, f"front_views.{k}") for k, v in enumerate(data["front_views"]))
    return PoseFile(poses, start, front, digest)


def _pose_entry(entry: Any, where: str) -> NDArray[np.float64]:
    if not isinstance(entry, dict):
        raise UserError(f"{where} must be a mapping with position_m and target_m, or matrix")
    keys = set(entry)
    try:
        if keys == {"matrix"}:
            m = np.asarray(entry["matrix"], dtype=np.float64)
            if m.shape != (4, 4):
                raise UserError(f"{where}.matrix must be 4 x 4, not {list(m.shape)}")
            return m
        if keys == {"position_m", "target_m"}:
            eye, target = (np.asarray(entry[k], dtype=np.float64) for k in ("position_m", "target_m"))
            if eye.shape != (3,) or target.shape != (3,):
                raise UserError(f"{where}: position_m and target_m must be [x, y, z]")
            if not np.all(np.isfinite(eye)) or not np.all(np.isfinite(target)):
                raise UserError(f"{where}: position_m and target_m must be finite")
            if np.linalg.norm(target - eye) < 1e-6:
                raise UserError(f"{where}: position_m and target_m coincide")
            return look_at(eye, target)
    except (TypeError, ValueError) as e:
        raise UserError(f"{where}: not numbers: {e}") from e
    raise UserError(f"{where} must have exactly position_m and target_m, or matrix; has {', '.join(sorted(keys))}")


def _check_pose(t: NDArray[np.float64], where: str) -> None:
    if not np.all(np.isfinite(t)):
        raise UserError(f"{where} is not finite")
    if not np.allclose(t[3], (0, 0, 0, 1), atol=1e-6):
        raise UserError(f"{where}: the last row of a pose must be [0, 0, 0, 1]")
    r = t[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise UserError(f"{where}: the rotation is not a proper rotation (orthonormal, determinant +1)")


def _angles(lo: float, hi: float, n: int) -> NDArray[np.float64]:
    return np.radians(np.linspace(lo, hi, n)) if n > 1 else np.radians(np.array([(lo + hi) / 2]))


def generate_viewpoints(cfg: ViewpointConfig, shelf: ShelfSpec | None = None) -> NDArray[np.float64]:
    """Camera-to-world poses ``[V, 4, 4]`` (OpenCV convention), ordered as the module docstring says.

    With ``shelf`` given, checks that every camera is in front of the shelf (y < 0), so no candidate
    view starts inside the shelf or behind its back board.
    """
    if cfg.poses_file is not None:
        out = read_poses_file(cfg.poses_file).poses.copy()
        fix = f"move the cameras of {cfg.poses_file} in front of the shelf"
    else:
        az = _angles(*cfg.azimuth_deg, cfg.grid)
        el = _angles(*cfg.elevation_deg, cfg.grid)
        ee, aa = np.meshgrid(el, az, indexing="ij")  # rows: elevation, columns: azimuth
        offsets = cfg.radius_m * np.stack([np.cos(ee) * np.sin(aa), -np.cos(ee) * np.cos(aa), np.sin(ee)],
                                          axis=-1).reshape(-1, 3)
        poses: list[NDArray[np.float64]] = []
        for tx in cfg.targets_x_m:
            target = np.array([tx, cfg.target_y_m, cfg.target_z_m])
            poses.extend(look_at(target + off, target) for off in offsets)
        out = np.stack(poses).astype(np.float64)
        fix = "increase radius_m, narrow azimuth_deg/elevation_deg or lower target_y_m"
    if shelf is not None and np.any(out[:, 1, 3] >= 0.0):
        bad = int(np.argmax(out[:, 1, 3]))
        raise UserError(
            f"viewpoint config puts cameras inside or behind the shelf (view {bad}: camera y = "
            f"{out[bad, 1, 3]:.3f} m; must be < 0, the open front): {fix}"
        )
    return out


def default_start_view(cfg: ViewpointConfig) -> int:
    """Index of the first view of an episode: the centre of the middle grid (slightly above the target);
    for a poses file its ``start_view``, else the most frontal view nearest the shelf's centre line."""
    if cfg.poses_file is not None:
        pf = read_poses_file(cfg.poses_file)
        if pf.start_view is not None:
            return pf.start_view
        p = pf.poses
        return int(np.argmin(np.abs(p[:, 0, 3]) + (1.0 - p[:, 1, 2])))  # |camera x| + (1 - cos to +y)
    g = len(cfg.targets_x_m) // 2
    return g * cfg.grid**2 + (cfg.grid // 2) * cfg.grid + cfg.grid // 2


def front_views(cfg: ViewpointConfig) -> list[int]:
    """Indices of the grasp skill's virtual front cameras: each grid's centre view; for a poses file
    its ``front_views``, else the most frontal view of the left, middle and right third of the views,
    ordered by where their optical axis crosses the plane y = ``target_y_m``."""
    if cfg.poses_file is None:
        g = cfg.grid
        centre = (g // 2) * g + g // 2
        return [k * g * g + centre for k in range(len(cfg.targets_x_m))]
    pf = read_poses_file(cfg.poses_file)
    if pf.front_views is not None:
        return list(pf.front_views)
    p = pf.poses
    forward_y = p[:, 1, 2]
    toward = np.flatnonzero(forward_y > 1e-6)  # views that look into the shelf (+y)
    if len(toward) == 0:
        return [default_start_view(cfg)]
    depth = (cfg.target_y_m - p[toward, 1, 3]) / forward_y[toward]
    x_cross = p[toward, 0, 3] + depth * p[toward, 0, 2]
    order = toward[np.argsort(x_cross, kind="stable")]
    return [int(part[np.argmax(forward_y[part])]) for part in np.array_split(order, min(3, len(order)))]
