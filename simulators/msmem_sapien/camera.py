"""The SAPIEN backend's camera (``CameraView``): SAPIEN's renderer when it works here, else open3d ray casting.

SAPIEN's own renderer (``Position`` picture -> z-depth, per-actor ``Segmentation`` -> ids and classes)
is used when a Vulkan device with SAPIEN's required features exists (on a CPU: Mesa >= 24 lavapipe, see
``setup_lavapipe.sh``); otherwise open3d ray casting over the same part meshes that ground truth
voxelises. Both put pixel centres at (u + 0.5, v + 0.5) and clip at the near plane.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import trimesh
from numpy.typing import NDArray

with warnings.catch_warnings():  # "Failed to find system libvulkan": SAPIEN then uses its bundled loader
    warnings.simplefilter("ignore", UserWarning)
    import sapien

from msmem_core.errors import UserError
from msmem_core.world.camera import Observation
from msmem_core.world.meshes import class_mesh
from msmem_core.world.scene import ObjectClass
from msmem_sapien.scene import _matrix, _sapien_pose

log = logging.getLogger(__name__)

LAVAPIPE_ENV = "MSMEM_LAVAPIPE_DIR"
"""Folder with ``lvp_icd.json`` made by ``setup_lavapipe.sh`` (default: ``<sys.prefix>/lavapipe``)."""



_NATIVE: tuple[bool, str] | None = None
"""Whether SAPIEN's renderer works in this process, and why (probed once: a failed Vulkan start sticks)."""
_KEEPALIVE: list[Any] = []


def lavapipe_icd() -> Path | None:
    """The ICD file ``setup_lavapipe.sh`` wrote, if any (``$MSMEM_LAVAPIPE_DIR`` or ``<sys.prefix>/lavapipe``)."""
    folder = Path(os.environ.get(LAVAPIPE_ENV) or Path(sys.prefix) / "lavapipe")
    icd = folder / "lvp_icd.json"
    return icd if icd.is_file() else None


def native_renderer() -> tuple[bool, str]:
    """Probe SAPIEN's renderer once per process: (available, what was found or why it failed).

    When ``VK_ICD_FILENAMES`` is unset and ``setup_lavapipe.sh`` has installed its private lavapipe,
    point the Vulkan loader at it first (the loader reads the variable when SAPIEN starts Vulkan).
    """
    global _NATIVE
    if _NATIVE is None:
        icd = lavapipe_icd()
        if icd is not None and not os.environ.get("VK_ICD_FILENAMES"):
            os.environ["VK_ICD_FILENAMES"] = str(icd)
        try:
            system = sapien.render.RenderSystem()
            _NATIVE = (True, f"SAPIEN renderer on {system.device.name}")
            # SAPIEN drops its compiled shader pipelines when the last render system goes; compiling
            # them takes seconds on lavapipe, so one system lives as long as the process.
            _KEEPALIVE.append(system)
        except RuntimeError as e:
            _NATIVE = (False, f"SAPIEN renderer unavailable ({e})")
    return _NATIVE


@functools.cache
def _class_soup(cls: ObjectClass) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Vertices and faces of a class's part meshes in its object frame (what ground truth voxelises)."""
    mesh = class_mesh(cls)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


_LOGGED_CAMERA: set[str] = set()


def _log_camera_once(path: str, detail: str) -> None:
    if path not in _LOGGED_CAMERA:
        _LOGGED_CAMERA.add(path)
        log.info("SAPIEN backend camera: %s (%s)", path, detail)


class CameraView:
    """The camera half of ``SapienSimulator``: which camera path to use, and rendering an observation.

    A mixin: it reads the simulator's ``config``, ``_native``, ``_rng``, ``_scene``, ``_sapien``,
    ``_camera``, ``_objects``, ``_ids`` and ``_pixel_rays`` and calls its ``_require_scene``,
    ``_shelf_meshes``, ``gripper_pose`` and ``_opening``.
    """

    def _choose_camera(self) -> bool:
        mode = self.config.renderer
        if mode == "raycast":
            _log_camera_once("raycast", "renderer: raycast in config")
            return False
        ok, detail = native_renderer()
        if ok:
            _log_camera_once("native", detail)
            return True
        if mode == "native":
            raise UserError(
                f"simulator 'sapien': renderer 'native' needs a Vulkan device: {detail}. Run "
                "simulators/msmem_sapien/setup_lavapipe.sh (CPU lavapipe) or set renderer: auto / raycast"
            )
        _log_camera_once("raycast", f"{detail}; open3d ray casting over the collision geometry")
        return False

    @property
    def camera_path(self) -> str:
        """``native`` (SAPIEN's renderer) or ``raycast`` (open3d over the collision geometry)."""
        return "native" if self._native else "raycast"

    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        """Render z-depth, labels and object ids from an OpenCV camera-to-world pose."""
        self._require_scene()
        cam = self.config.camera
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        depth, object_ids = self._render_native(c2w) if self._native else self._render_raycast(c2w)
        oids = sorted(self._objects)
        id_lut = np.zeros(max(oids, default=0) + 2, dtype=np.int16)  # indexed by object id + 1
        for oid in oids:
            id_lut[oid + 1] = self._objects[oid].class_id
        if self.config.label_noise > 0.0:
            # Structured noise: a visible object is relabelled as a whole for this view, never per pixel.
            visible = sorted(int(i) for i in np.unique(object_ids) if i >= 0)
            flips = self._rng.random(len(visible)) < self.config.label_noise
            for oid, flip in zip(visible, flips, strict=True):
                obj = self._objects[oid]
                if flip and obj.confusable_id is not None:
                    id_lut[oid + 1] = obj.confusable_id
        labels = id_lut[object_ids + 1]
        return Observation(
            depth=depth.astype(np.float32),
            labels=labels.astype(np.int16),
            intrinsics=cam.intrinsics,
            camera_to_world=c2w.copy(),
            object_ids=object_ids.astype(np.int32),
            meta={"camera": self.camera_path},
        )

    def _render_native(self, c2w: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """SAPIEN's renderer: ``Position`` (OpenGL camera frame) -> z-depth, ``Segmentation`` -> ids."""
        assert self._sapien is not None
        assert self._camera is not None
        cam = self.config.camera
        # SAPIEN camera entity axes: x forward, y left, z up (OpenCV: z forward, x right, y down).
        mount = c2w.copy()
        mount[:3, :3] = c2w[:3, :3] @ np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        self._camera.entity.pose = _sapien_pose(mount)
        self._sapien.update_render()
        self._camera.take_picture()
        position = self._camera.get_picture("Position")
        seg = self._camera.get_picture("Segmentation")[..., 1].astype(np.int64)
        depth = -position[..., 2].astype(np.float64)
        depth[(position[..., 3] >= 1.0) | (depth > cam.far_m) | (depth <= 0.0)] = 0.0
        lut = np.full(max(self._ids, default=0) + 2, -1, dtype=np.int64)
        for sid, oid in self._ids.items():
            if oid >= 0:
                lut[sid] = oid
        seg = np.where(seg < len(lut), seg, len(lut) - 1)
        ids = lut[seg]
        ids[depth == 0.0] = -1
        return depth, ids

    def _render_raycast(self, c2w: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """open3d ray casting over the part meshes at their current poses (and shelf and gripper boxes).

        One triangle soup; each triangle's owner (object id, or -1 for shelf and gripper) gives the ids.
        Rays start on the near plane with a unit optical-axis component, so ``near + t_hit`` is z-depth.
        """
        assert self._scene is not None
        cam = self.config.camera
        verts: list[NDArray[np.float64]] = []
        faces: list[NDArray[np.int64]] = []
        owners: list[NDArray[np.int64]] = []
        count = 0

        def add(v: NDArray[np.float64], f: NDArray[np.int64], owner: int) -> None:
            nonlocal count
            verts.append(v)
            faces.append(f + count)
            owners.append(np.full(len(f), owner, dtype=np.int64))
            count += len(v)

        for oid, obj in self._objects.items():
            v, f = _class_soup(obj.spec.object_class)
            t = _matrix(obj.entity.pose)
            add(v @ t[:3, :3].T + t[:3, 3], f, oid)
        for m in [*self._shelf_meshes(self._scene.shelf), self._gripper_world_mesh()]:
            add(np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64), -1)
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.concatenate(verts), dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.concatenate(faces), dtype=np.uint32)),
        )
        if self._pixel_rays is None:
            self._pixel_rays = cam.pixel_rays(1).reshape(-1, 3).astype(np.float32)
        d_world = self._pixel_rays @ c2w[:3, :3].T.astype(np.float32)
        origin = (c2w[:3, 3] + cam.near_m * d_world).astype(np.float32)
        ans = rc.cast_rays(o3d.core.Tensor.from_numpy(np.concatenate([origin, d_world], axis=1)))
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t_hit) & (t_hit <= cam.far_m - cam.near_m)
        owner = np.concatenate([*owners, np.array([-1], dtype=np.int64)])
        ids = owner[np.where(hit, prim, len(owner) - 1)]
        depth = np.where(hit, t_hit + cam.near_m, 0.0)
        shape = (cam.height_px, cam.width_px)
        return depth.reshape(shape), ids.reshape(shape)

    def _gripper_world_mesh(self) -> Any:
        pose = self.gripper_pose()
        parts = []
        for centre, half in self.config.gripper.boxes(self._opening()):
            t = pose.copy()
            t[:3, 3] = pose[:3, 3] + pose[:3, :3] @ centre
            parts.append(trimesh.creation.box(extents=2 * half, transform=t))
        return trimesh.util.concatenate(parts)
