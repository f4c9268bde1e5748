"""The conformance suite a ``Simulator`` backend runs to prove it follows the interface and its conventions.

Usage, inside a pytest test of the backend::

    from msmem_core.testing.conformance import simulator_conformance

    def test_my_backend_conforms():
        simulator_conformance(lambda: MySimulator(label_noise=0.0), noise_free=True)

The suites for skills, effect models and observation models (``skill_conformance``,
``effect_model_conformance``, ``observation_model_conformance``) live in
``msmem_core.testing.plugin_conformance`` and are importable from here too. Every suite checks its
argument first: handing it anything but a factory of what it tests raises ``ConformanceUsageError``
in one line naming what it expected and what it got.

Each ``check_*`` function is public, so a backend can also run the checks one by one. The checks use
only the ``Simulator`` vocabulary and build their own small scenes; tolerances are those every
backend should meet (1 cm placement after settling, 5 mm for depth back-projection and gripper
moves, 1e-6 for snapshot round trips).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import GRIPPER_ID, Simulator
from msmem_core.testing.builders import conformance_scene
from msmem_core.testing.plugin_conformance import (
    ConformanceError,
    ConformanceUsageError,
    built,
    effect_model_conformance,
    observation_model_conformance,
    skill_conformance,
)
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.geometry import look_at, quat_to_matrix, rotation_angle_deg
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import ObjectSpec, SceneSpec

PLACEMENT_TOL_M = 0.01
PLACEMENT_TOL_DEG = 3.0
SURFACE_TOL_M = 0.005
GRIPPER_TOL_M = 0.005
GRIPPER_TOL_DEG = 2.0
OPENING_TOL_M = 0.002
ROUND_TRIP_TOL = 1e-6


# ------------------------------------------------------------------------------------------- scenes
def single_object_scene(class_name: str, position_m: tuple[float, float, float], object_id: int = 7) -> SceneSpec:
    """One upright object (yaw 0) in the default shelf."""
    return SceneSpec(
        name=f"single_{class_name}",
        objects=(ObjectSpec(id=object_id, class_name=class_name, position_m=position_m),),
    )


def front_view(scene: SceneSpec) -> NDArray[np.float64]:
    """A camera in front of and above the shelf, looking at the middle of its floor."""
    s = scene.shelf
    return look_at((0.0, -0.45, s.height_m + 0.07), (0.0, s.depth_m / 2, 0.06))


def gripper_pose(position: Iterable[float], approach: Iterable[float], closing: Iterable[float]) -> NDArray[np.float64]:
    """A ``GripperSpec`` pose from its origin, approach axis (z) and closing axis (x)."""
    z = np.asarray(approach, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.asarray(closing, dtype=np.float64)
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = x, np.cross(z, x), z, np.asarray(list(position), dtype=np.float64)
    return t


# ------------------------------------------------------------------------------------------- geometry
def surface_distance(obj: ObjectSpec, pose: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (N,) of world points to the union of the object's parts at ``pose``.

    Exact outside the object; inside it is the distance to the nearest part's surface, which is
    all a surface test needs.
    """
    local = (points - pose[:3, 3]) @ pose[:3, :3]  # world -> object frame
    best = np.full(len(points), np.inf)
    for part in obj.object_class.parts:
        q = (local - np.asarray(part.position_m)) @ quat_to_matrix(part.quat_xyzw)  # object -> part frame
        if part.kind == "box":
            d = np.abs(q) - np.asarray(part.size_m) / 2
        else:
            radius, height = part.size_m
            d = np.stack([np.hypot(q[:, 0], q[:, 1]) - radius, np.abs(q[:, 2]) - height / 2], axis=1)
        outside = np.linalg.norm(np.maximum(d, 0.0), axis=1)
        sd = np.where(np.all(d < 0, axis=1), d.max(axis=1), outside)
        best = np.minimum(best, sd)
    return best


def _object_points(obs: Observation, object_id: int) -> NDArray[np.float64]:
    """World points of the pixels that see ``object_id``, by ``Observation.points_world`` (pixel centres)."""
    assert obs.object_ids is not None
    return obs.points_world()[obs.object_ids[obs.depth > 0] == object_id]


def _object_pixels(obs: Observation, object_id: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    assert obs.object_ids is not None
    v, u = np.nonzero(obs.object_ids == object_id)
    return v, u


# ------------------------------------------------------------------------------------------- checks
def check_reset(sim: Simulator, scene: SceneSpec) -> None:
    """``reset`` builds every object at its pose (after settling, for a scene without overlaps)."""
    sim.reset(scene)
    poses = sim.object_poses()
    assert set(poses) == {o.id for o in scene.objects}, f"object_poses ids {sorted(poses)}"
    for o in scene.objects:
        t = poses[o.id]
        assert t.shape == (4, 4)
        err = float(np.linalg.norm(t[:3, 3] - np.asarray(o.position_m)))
        assert err < PLACEMENT_TOL_M, f"object {o.id} ({o.class_name}) settled {err * 100:.1f} cm from its pose"
        ang = rotation_angle_deg(t, o.pose())
        assert ang < PLACEMENT_TOL_DEG, f"object {o.id} settled rotated by {ang:.1f} deg"
    assert sim.capabilities().name, "capabilities().name must not be empty"


def check_observation(sim: Simulator, scene: SceneSpec, camera: CameraConfig, *, noise_free: bool) -> None:
    """``observe`` returns arrays per ``CameraConfig``; depth back-projects onto the objects' surfaces;
    labels follow ``object_ids`` (exactly, or up to whole-object structured noise)."""
    sim.reset(scene)
    view = front_view(scene)
    obs = sim.observe(view)
    shape = (camera.height_px, camera.width_px)
    assert obs.object_ids is not None, "backends report ground-truth object_ids (tests and metrics use them)"
    for name, arr, dtype in (
        ("depth", obs.depth, np.float32),
        ("labels", obs.labels, np.int16),
        ("object_ids", obs.object_ids, np.int32),
    ):
        assert arr.shape == shape, f"{name} has shape {arr.shape}, expected {shape}"
        assert arr.dtype == dtype, f"{name} has dtype {arr.dtype}, expected {np.dtype(dtype)}"
    np.testing.assert_allclose(obs.intrinsics, camera.intrinsics, rtol=1e-9)
    np.testing.assert_allclose(obs.camera_to_world, view, atol=1e-12)
    d = obs.depth
    assert np.all(np.isfinite(d)), "depth must be finite"
    assert np.all(d >= 0), "depth must be >= 0"
    hit = d > 0
    assert hit.mean() > 0.5, "the shelf should fill most of a front view"
    assert np.all((d[hit] >= camera.near_m * 0.999) & (d[hit] <= camera.far_m)), "depth outside [near, far]"

    poses = sim.object_poses()
    present = {int(i) for i in np.unique(obs.object_ids) if i >= 0}
    assert present <= set(poses), f"object_ids name unknown objects {present - set(poses)}"
    assert present, "no object visible in the front view of the scene"
    assert np.all(obs.labels[obs.object_ids < 0] == 0), "pixels of no object must be labelled background (0)"
    for o in scene.objects:
        if o.id not in present:
            continue
        sd = surface_distance(o, poses[o.id], _object_points(obs, o.id))
        worst = float(np.abs(sd).max())
        assert worst < SURFACE_TOL_M, f"object {o.id}: back-projected depth {worst * 1000:.1f} mm off its surface"
        v, u = _object_pixels(obs, o.id)
        seen = set(np.unique(obs.labels[v, u]).tolist())
        assert len(seen) == 1, f"object {o.id} carries several labels {seen} in one view (noise must be structured)"
        allowed = {o.class_id}
        if not noise_free and o.object_class.confusable_id is not None:
            allowed.add(o.object_class.confusable_id)
        assert seen <= allowed, f"object {o.id} labelled {seen}, expected one of {allowed}"


def _covered_pixels(lo: float, hi: float) -> tuple[int, int, float]:
    """First and last pixel index whose centre (i + 0.5) lies in (lo, hi), and the smaller distance
    (in pixels) of an edge to a pixel centre: below ~0.15 px the renderer may round either way."""
    first, last = math.ceil(lo - 0.5), math.floor(hi - 0.5)
    margin = min(abs(lo - 0.5 - round(lo - 0.5)), abs(hi - 0.5 - round(hi - 0.5)))
    return first, last, margin


def check_z_depth(sim: Simulator) -> None:
    """A camera facing a box face head-on sees the whole face at one depth (z, not the ray length),
    and the face covers exactly the pixels whose centres project inside it."""
    scene = single_object_scene("sugar_box", (0.0, 0.2, 0.0))
    sim.reset(scene)
    box = scene.objects[0]
    size = box.object_class.parts[0].size_m
    pose = sim.object_poses()[box.id]
    face_y = pose[1, 3] - size[1] / 2
    dist = 0.24
    mid_z = pose[2, 3] + size[2] / 2
    eye = np.array([pose[0, 3], face_y - dist, mid_z])
    obs = sim.observe(look_at(eye, eye + np.array([0.0, 1.0, 0.0])))
    v, u = _object_pixels(obs, box.id)
    z = obs.depth[v, u]
    assert len(z), "the box face is not visible"
    assert np.abs(z - dist).max() < 0.002, f"face depth spans {z.min():.4f}..{z.max():.4f}, not {dist}"
    k = obs.intrinsics
    extents = {"u": (u, k[0, 2], k[0, 0] * size[0] / 2 / dist), "v": (v, k[1, 2], k[1, 1] * size[2] / 2 / dist)}
    for axis, (pix, centre, half_px) in extents.items():
        first, last, margin = _covered_pixels(centre - half_px, centre + half_px)
        slack = 0 if margin > 0.15 else 1
        span = f"face spans {axis} = {pix.min()}..{pix.max()}, expected {first}..{last} (pixel centres at i + 0.5)"
        assert abs(pix.min() - first) <= slack, span
        assert abs(pix.max() - last) <= slack, span


def check_camera_convention(sim: Simulator) -> None:
    """OpenCV camera frame: a box to the camera's right is in the right half, one above in the top half."""
    scene = single_object_scene("sugar_box", (0.0, 0.2, 0.0))
    sim.reset(scene)
    oid = scene.objects[0].id
    h = 0.0875
    right = sim.observe(look_at((-0.15, -0.3, h), (-0.15, 0.5, h)))
    v, u = _object_pixels(right, oid)
    w_px = right.depth.shape[1]
    assert len(u), "the box is not visible"
    assert u.min() > w_px / 2, "a box to the camera's right must appear in the right half"
    above = sim.observe(look_at((0.0, -0.3, 0.01), (0.0, 0.5, 0.01)))
    v, u = _object_pixels(above, oid)
    h_px = above.depth.shape[0]
    assert len(v), "the box is not visible"
    assert np.mean(v < h_px / 2) > 0.9, "a box above the camera must appear in the top half (row 0 = top)"


def check_gripper(sim: Simulator, gripper: GripperSpec) -> None:
    """In free space the gripper goes where it is told and its fingers reach the requested opening."""
    sim.reset(SceneSpec(name="empty"))
    a = gripper_pose((0.0, -0.25, 0.15), (0, 1, 0), (1, 0, 0))
    reached = sim.move_gripper([a])
    _assert_pose_close(reached, a, "move_gripper to a free pose")
    b = a.copy()
    b[:3, 3] += (0.05, -0.02, 0.03)
    b[:3, :3] = quat_to_matrix((0.0, np.sin(np.pi / 12), 0.0, np.cos(np.pi / 12))) @ a[:3, :3]
    c = b.copy()
    c[:3, :3] = quat_to_matrix((np.sin(np.pi / 16), 0.0, 0.0, np.cos(np.pi / 16))) @ b[:3, :3]
    reached = sim.move_gripper([b, c], speed_mps=0.2)
    _assert_pose_close(reached, c, "move_gripper through two waypoints")
    _assert_pose_close(sim.gripper_pose(), reached, "gripper_pose() after a move")
    for opening in (0.05, 0.0, gripper.max_opening_m * 0.9, 0.03):
        got = sim.set_gripper(opening)
        assert abs(got - opening) < OPENING_TOL_M, f"set_gripper({opening}) reached {got}"
    assert sim.held_object() is None, "nothing is held in free space"
    assert not [k for k in sim.contacts() if GRIPPER_ID in (k.body_a, k.body_b)], "gripper touches something"


def _assert_pose_close(got: NDArray[np.float64], want: NDArray[np.float64], what: str) -> None:
    err = float(np.linalg.norm(got[:3, 3] - want[:3, 3]))
    ang = rotation_angle_deg(got, want)
    msg = f"{what}: off by {err * 1000:.1f} mm / {ang:.2f} deg"
    assert err < GRIPPER_TOL_M, msg
    assert ang < GRIPPER_TOL_DEG, msg


def push_along_y(sim: Simulator, obj: ObjectSpec, distance_m: float, height_m: float = 0.03) -> None:
    """Push an object towards the back with the closed gripper pointing down, fingertips at ``height_m``."""
    pose = sim.object_poses()[obj.id]
    reach = obj.object_class.footprint_radius_m
    x, y = pose[0, 3], pose[1, 3]
    start = gripper_pose((x, y - reach - 0.04, height_m), (0, 0, -1), (1, 0, 0))
    end = gripper_pose((x, y - reach + distance_m, height_m), (0, 0, -1), (1, 0, 0))
    sim.move_gripper([start, end], opening_m=0.0)


def _assert_poses_equal(got: dict[int, NDArray[np.float64]], want: dict[int, NDArray[np.float64]], what: str) -> None:
    assert set(got) == set(want), f"{what}: objects {sorted(got)} != {sorted(want)}"
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=ROUND_TRIP_TOL, err_msg=f"{what}: object {k}")


def check_snapshot_restore(sim: Simulator) -> None:
    """``restore`` brings back a snapshot's poses exactly, across a push and a ``remove_object``."""
    scene = conformance_scene()
    sim.reset(scene)
    view = front_view(scene)
    tok0 = sim.snapshot()
    poses0, grip0, depth0 = sim.object_poses(), sim.gripper_pose(), sim.observe(view).depth
    brick = scene.objects[1]
    push_along_y(sim, brick, 0.05)
    poses1, grip1 = sim.object_poses(), sim.gripper_pose()
    moved = float(np.linalg.norm(poses1[brick.id][:3, 3] - poses0[brick.id][:3, 3]))
    assert moved > 0.02, f"the pushed object moved only {moved * 100:.1f} cm"
    tok1 = sim.snapshot()
    sim.remove_object(0)
    assert 0 not in sim.object_poses()
    tok2 = sim.snapshot()

    sim.restore(tok0)
    _assert_poses_equal(sim.object_poses(), poses0, "restore before push and removal")
    np.testing.assert_allclose(sim.gripper_pose(), grip0, atol=ROUND_TRIP_TOL)
    depth = sim.observe(view).depth
    assert np.mean(np.abs(depth - depth0) > 1e-3) < 1e-3, "the restored scene renders differently"
    sim.restore(tok2)
    _assert_poses_equal(sim.object_poses(), {k: v for k, v in poses1.items() if k != 0}, "restore after removal")
    sim.restore(tok1)
    _assert_poses_equal(sim.object_poses(), poses1, "restore between push and removal")
    np.testing.assert_allclose(sim.gripper_pose(), grip1, atol=ROUND_TRIP_TOL)


def check_remove_object(sim: Simulator) -> None:
    """A removed object vanishes from ``object_poses`` and from depth images."""
    scene = conformance_scene()
    sim.reset(scene)
    view = front_view(scene)
    before = sim.observe(view)
    oid = scene.objects[0].id
    v, u = _object_pixels(before, oid)
    assert len(v) > 100, "the object to remove should be visible"
    sim.remove_object(oid)
    assert oid not in sim.object_poses()
    after = sim.observe(view)
    assert after.object_ids is not None
    assert not np.any(after.object_ids == oid), "removed object still rendered"
    behind = (after.depth[v, u] == 0) | (after.depth[v, u] > before.depth[v, u] + 1e-4)
    assert behind.mean() > 0.99, "depth where the removed object was did not move back"


def check_grasp(sim: Simulator, gripper: GripperSpec) -> None:
    """Closing the fingers around a small box from above holds it (friction only) through a lift."""
    scene = single_object_scene("foam_brick", (0.1, 0.2, 0.0))
    sim.reset(scene)
    brick = scene.objects[0]
    width = brick.object_class.parts[0].size_m[1]
    z0 = sim.object_poses()[brick.id][2, 3]

    def above(tip_z: float) -> NDArray[np.float64]:
        return gripper_pose((0.1, 0.2, tip_z), (0, 0, -1), (0, 1, 0))

    sim.move_gripper([above(0.12), above(0.015)], opening_m=gripper.max_opening_m)
    opening = sim.set_gripper(0.0)
    assert abs(opening - width) < 0.005, f"fingers closed to {opening * 1000:.1f} mm on a {width * 1000:.0f} mm box"
    assert sim.held_object() == brick.id, f"held_object() is {sim.held_object()}, expected {brick.id}"
    gripper_contacts = [k for k in sim.contacts() if GRIPPER_ID in (k.body_a, k.body_b)]
    touching = {k.body_a if k.body_b == GRIPPER_ID else k.body_b for k in gripper_contacts}
    assert brick.id in touching, "contacts() must list the gripper touching the grasped object"
    sim.move_gripper([above(0.115)])
    rose = sim.object_poses()[brick.id][2, 3] - z0
    assert rose > 0.09, f"the grasped object rose {rose * 100:.1f} cm with a 10 cm lift"
    assert sim.held_object() == brick.id
    sim.set_gripper(gripper.max_opening_m)
    sim.step(1.0)
    assert sim.held_object() is None, "released object still held"
    assert sim.object_poses()[brick.id][2, 3] < 0.06, "released object did not fall"


def _build_simulator(name: str) -> Simulator:
    from msmem_core.sim.build import build_simulator

    return build_simulator(name, label_noise=0.0)


def simulator_conformance(
    factory: Callable[[], Simulator] | str,
    scene: SceneSpec | None = None,
    *,
    noise_free: bool = False,
    camera: CameraConfig | None = None,
    gripper: GripperSpec | None = None,
) -> None:
    """Run every check on one simulator from ``factory`` (closed at the end): a class or function
    returning a fresh ``Simulator``, or a registered simulator name (built with ``label_noise=0``).

    ``scene`` (default ``conformance_scene()``, no overlaps) is used by the placement and observation
    checks; the others build their own. ``noise_free=True`` demands labels equal to the class; otherwise
    a whole object may carry its confusable class. ``camera`` and ``gripper`` are the backend's
    configuration (defaults: ``CameraConfig()``, ``GripperSpec()``).
    """
    sim: Simulator = built(factory, Simulator, "simulator_conformance", "a factory returning a "
                           "msmem_core.interfaces.Simulator (e.g. `lambda: MySimulator(...)`) or a registered "
                           "simulator name", _build_simulator)
    scene = scene or conformance_scene()
    camera = camera or CameraConfig()
    gripper = gripper or GripperSpec()
    try:
        check_reset(sim, scene)
        check_observation(sim, scene, camera, noise_free=noise_free)
        check_z_depth(sim)
        check_camera_convention(sim)
        check_gripper(sim, gripper)
        check_snapshot_restore(sim)
        check_remove_object(sim)
        check_grasp(sim, gripper)
    finally:
        sim.close()


__all__ = [
    "ConformanceError",
    "ConformanceUsageError",
    "check_camera_convention",
    "check_grasp",
    "check_gripper",
    "check_observation",
    "check_remove_object",
    "check_reset",
    "check_snapshot_restore",
    "check_z_depth",
    "conformance_scene",
    "effect_model_conformance",
    "front_view",
    "gripper_pose",
    "observation_model_conformance",
    "push_along_y",
    "simulator_conformance",
    "single_object_scene",
    "skill_conformance",
    "surface_distance",
]
