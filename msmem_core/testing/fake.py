"""A deterministic in-memory Simulator for unit tests of loops (objects never move unless told)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import Capabilities, Contact, Simulator
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.scene import SceneSpec


class FakeSimulator(Simulator):
    """Renders only the shelf's back wall (a plane at y = depth) as depth; labels are background.

    Enough to drive the MSAS loop, the observation model and the run folder in unit tests.
    """

    def __init__(self, camera: CameraConfig | None = None) -> None:
        self.camera = camera or CameraConfig(width_px=64, height_px=48)
        self.scene: SceneSpec | None = None
        self.poses: dict[int, NDArray[np.float64]] = {}
        self.pose = np.eye(4)
        self.opening = 0.0
        self.calls: list[str] = []

    def reset(self, scene: SceneSpec) -> None:
        self.scene = scene
        self.poses = {o.id: o.pose() for o in scene.objects}
        self.calls.append("reset")

    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        assert self.scene is not None, "reset first"
        self.calls.append("observe")
        cam = self.camera
        dirs = cam.pixel_rays(1) @ camera_to_world[:3, :3].T  # world directions with camera z = 1
        wall_y = self.scene.shelf.depth_m
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (wall_y - camera_to_world[1, 3]) / dirs[..., 1]
        depth = np.where((z > cam.near_m) & (z < cam.far_m), z, 0.0).astype(np.float32)
        labels = np.zeros(depth.shape, dtype=np.int16)
        return Observation(depth, labels, cam.intrinsics, camera_to_world.copy())

    def move_gripper(self, waypoints: Sequence[NDArray[np.float64]], opening_m: float | None = None,
                     speed_mps: float = 0.1) -> NDArray[np.float64]:
        if opening_m is not None:
            self.opening = opening_m
        self.pose = np.asarray(waypoints[-1], dtype=np.float64).copy()
        self.calls.append("move_gripper")
        return self.pose

    def set_gripper(self, opening_m: float) -> float:
        self.opening = opening_m
        return opening_m

    def park_gripper(self) -> None:
        self.pose = np.eye(4)
        self.pose[2, 3] = 2.0

    def gripper_pose(self) -> NDArray[np.float64]:
        return self.pose.copy()

    def contacts(self) -> list[Contact]:
        return []

    def held_object(self) -> int | None:
        return None

    def remove_object(self, object_id: int) -> None:
        self.poses.pop(object_id)

    def object_poses(self) -> dict[int, NDArray[np.float64]]:
        return {k: v.copy() for k, v in self.poses.items()}

    def step(self, seconds: float) -> None:
        pass

    def snapshot(self) -> Any:
        return ({k: v.copy() for k, v in self.poses.items()}, self.pose.copy(), self.opening)

    def restore(self, token: Any) -> None:
        poses, pose, opening = token
        self.poses = {k: v.copy() for k, v in poses.items()}
        self.pose, self.opening = pose.copy(), opening

    def capabilities(self) -> Capabilities:
        return Capabilities(name="fake", physics=False, notes="back wall only; for loop unit tests")
