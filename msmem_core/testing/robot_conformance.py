"""Conformance suite for robots (``msmem_core.interfaces.Robot``), in the manner of ``skill_conformance``.

Usage, inside a pytest test of the plugin::

    from msmem_core.testing import robot_conformance

    def test_my_robot_conforms():
        report = robot_conformance(MyRobot)          # or lambda: MyRobot(MyConfig(...)), or "my-robot"
        assert report.reachable_views > 200          # the plugin's own expectations

What it checks, without trusting the robot's own kinematics: the model and the mounts are well formed;
the reachable-views answer is a bool mask that agrees with ``reach_camera`` view by view; every answer
called reachable lies inside the joint limits, is free of collisions by the robot's own ``collisions``
and, for a robot with a URDF, puts the flange where it was asked by an *independent* forward kinematics
(a pybullet client of the suite's own loading the same URDF at ``RobotModel.base_pose``) with no link
inside a shelf board; poses far away or inside a board are refused with a one-line reason; answers are
deterministic; paths through a reachable pose are followed and paths that leave the workspace are
refused naming their point; the points the arm is drawn by (``link_points``) start at the base and pass
the flange. A robot without an arm (``Robot.arm = False``) must reach everything.

A failed check raises ``ConformanceError`` naming the robot and the rule; ``ConformanceUsageError`` when
the argument is not a robot factory. Every ``check_*`` function is public.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import Reach, Robot, RobotModel
from msmem_core.testing.plugin_conformance import ConformanceError, ConformanceUsageError, built
from msmem_core.util.quiet import quiet_stdio
from msmem_core.world.geometry import matrix_to_quat, pose_matrix, rotation_angle_deg
from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

FK_POSITION_M = 0.01
"""Largest flange position error an answer called reachable may have, by the suite's own forward kinematics."""
FK_ANGLE_DEG = 5.0
"""Largest flange orientation error (degrees) of an answer called reachable."""
PENETRATION_M = 0.002
"""A link deeper than this inside a shelf board (the suite's own check) is a collision."""
FAR_M = 5.0
"""A pose this far above the base is out of reach of any arm the suite expects."""


@dataclass
class RobotReport:
    """What ``robot_conformance`` saw, for the plugin's own assertions."""

    name: str
    arm: bool
    views: int
    """Candidate views asked (the default viewpoint set unless given)."""
    reachable_views: int
    checked: int
    """Reachable answers verified independently (forward kinematics, limits, collisions)."""


def _fail(msg: str) -> None:
    raise ConformanceError(msg)


def _who(robot: Robot) -> str:
    try:
        name = robot.model().name
    except Exception:  # the model check reports a broken model itself
        name = "?"
    return f"robot {name!r} ({type(robot).__name__})"


def _is_rigid(t: object) -> bool:
    if not (isinstance(t, np.ndarray) and t.shape == (4, 4) and np.all(np.isfinite(t))):
        return False
    r = t[:3, :3]
    return bool(np.allclose(r.T @ r, np.eye(3), atol=1e-6) and abs(np.linalg.det(r) - 1.0) < 1e-6
                and np.allclose(t[3], [0, 0, 0, 1]))


# ------------------------------------------------------------------------------------------- checks
def check_model(robot: Robot) -> RobotModel:
    """``model()`` is a ``RobotModel`` with a rigid 4x4 base pose, as many lower and upper limits as
    joint names with lower <= upper, and, for a robot with an arm, an existing URDF and a flange link."""
    who = _who(robot)
    m = robot.model()
    if not isinstance(m, RobotModel):
        _fail(f"{who}: model() must return a msmem_core.interfaces.RobotModel, got {type(m).__name__}")
    if not _is_rigid(np.asarray(m.base_pose, dtype=np.float64)):
        _fail(f"{who}: RobotModel.base_pose must be a rigid 4x4 transform (orthonormal rotation, last row 0 0 0 1)")
    n = len(m.joint_names)
    if len(m.joint_lower) != n or len(m.joint_upper) != n:
        _fail(f"{who}: RobotModel has {n} joint names but {len(m.joint_lower)} lower and {len(m.joint_upper)} "
              "upper limits")
    bad = [name for name, lo, hi in zip(m.joint_names, m.joint_lower, m.joint_upper, strict=True) if not lo <= hi]
    if bad:
        _fail(f"{who}: joint limits with lower > upper: {', '.join(bad)}")
    if robot.arm:
        if m.urdf is None or not Path(m.urdf).is_file():
            _fail(f"{who}: a robot with an arm must name an existing URDF (RobotModel.urdf), got {m.urdf!r}")
        if not m.flange_link:
            _fail(f"{who}: a robot with an arm must name its flange link (RobotModel.flange_link)")
        if n == 0:
            _fail(f"{who}: a robot with an arm must list the joints its IK solves for (RobotModel.joint_names)")
    return m


def check_mounts(robot: Robot) -> None:
    """``camera_mount()`` and ``tool_mount()`` are rigid 4x4 transforms."""
    who = _who(robot)
    for what in ("camera_mount", "tool_mount"):
        t = getattr(robot, what)()
        if not _is_rigid(np.asarray(t, dtype=np.float64) if isinstance(t, np.ndarray) else t):
            _fail(f"{who}: {what}() must return a rigid 4x4 transform (numpy array)")


def check_refusal(reach: object, who: str, what: str) -> None:
    """``reach`` is a ``Reach`` saying unreachable, with no configuration and a one-line reason."""
    if not isinstance(reach, Reach):
        _fail(f"{who}: {what}: ik must return a msmem_core.interfaces.Reach, got {type(reach).__name__}")
    assert isinstance(reach, Reach)
    if reach.reachable:
        _fail(f"{who}: {what} was called reachable")
    if reach.joints is not None:
        _fail(f"{who}: {what}: an unreachable answer must carry no configuration (joints=None)")
    if not reach.reason or "\n" in reach.reason:
        _fail(f"{who}: {what}: an unreachable answer needs a one-line reason, got {reach.reason!r}")


class _Kinematics:
    """The suite's own pybullet client: the robot's URDF at its base pose, and the shelf's boards."""

    def __init__(self, model: RobotModel, shelf: ShelfSpec) -> None:
        with quiet_stdio():
            import pybullet
            from pybullet_utils.bullet_client import BulletClient

            self.client = c = BulletClient(connection_mode=pybullet.DIRECT)
            base = model.base_pose
            assert model.urdf is not None
            self.body = c.loadURDF(model.urdf, [float(x) for x in base[:3, 3]],
                                   [float(x) for x in matrix_to_quat(base[:3, :3])], useFixedBase=True)
        joints, links = {}, {}
        for j in range(c.getNumJoints(self.body)):
            info = c.getJointInfo(self.body, j)
            joints[info[1].decode()] = j
            links[info[12].decode()] = j
        missing = [n for n in model.joint_names if n not in joints]
        if missing:
            _fail(f"robot {model.name!r}: joints {missing} are not in its URDF {model.urdf}")
        if model.flange_link not in links:
            _fail(f"robot {model.name!r}: flange link {model.flange_link!r} is not in its URDF {model.urdf}")
        self.joints = [joints[n] for n in model.joint_names]
        self.flange = links[str(model.flange_link)]
        self.boards = []
        for centre, half in shelf.boards():
            shape = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[float(h) for h in half])
            self.boards.append(c.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape,
                                                 basePosition=[float(x) for x in centre]))

    def flange_pose(self, q: tuple[float, ...]) -> NDArray[np.float64]:
        for j, v in zip(self.joints, q, strict=True):
            self.client.resetJointState(self.body, j, float(v))
        s = self.client.getLinkState(self.body, self.flange, computeForwardKinematics=True)
        return pose_matrix(s[4], s[5])

    def penetration(self) -> float:
        """Deepest penetration (m, >= 0) of any link into a board, in the configuration last set."""
        depth = 0.0
        for b in self.boards:
            for p in self.client.getClosestPoints(self.body, b, distance=0.0):
                depth = max(depth, -float(p[8]))
        return depth

    def close(self) -> None:
        self.client.disconnect()


def check_answer(robot: Robot, reach: Reach, target: NDArray[np.float64], shelf: ShelfSpec, what: str,
                 kin: _Kinematics | None) -> None:
    """An answer called reachable: a configuration of the model's joints inside their limits, no
    collisions by ``robot.collisions``, and (with ``kin``, the URDF loaded independently) the flange
    within ``FK_POSITION_M`` / ``FK_ANGLE_DEG`` of ``target`` with no link inside a board."""
    who, m = _who(robot), robot.model()
    if reach.joints is None or len(reach.joints) != len(m.joint_names):
        count = None if reach.joints is None else len(reach.joints)
        _fail(f"{who}: {what}: a reachable answer needs one value per joint of the model "
              f"({len(m.joint_names)}), got {count}")
    joints = tuple(reach.joints or ())
    q = np.asarray(joints, dtype=np.float64)
    lo, hi = np.asarray(m.joint_lower), np.asarray(m.joint_upper)
    out = [n for n, v, a, b in zip(m.joint_names, q, lo, hi, strict=True) if not a - 1e-6 <= v <= b + 1e-6]
    if out:
        _fail(f"{who}: {what}: the answer leaves the joint limits at {', '.join(out)}")
    hits = robot.collisions(joints, shelf)
    if hits:
        _fail(f"{who}: {what}: called reachable, but collisions() of its configuration reports {hits[:3]}")
    if kin is None:
        return
    got = kin.flange_pose(joints)
    perr = float(np.linalg.norm(got[:3, 3] - target[:3, 3]))
    aerr = rotation_angle_deg(got, target)
    if perr > FK_POSITION_M or aerr > FK_ANGLE_DEG:
        _fail(f"{who}: {what}: called reachable, but forward kinematics of the URDF puts the flange "
              f"{perr * 1000:.1f} mm and {aerr:.1f} deg from the asked pose")
    depth = kin.penetration()
    if depth > PENETRATION_M:
        _fail(f"{who}: {what}: called reachable, but a link is {depth * 1000:.1f} mm inside a shelf board")


def check_link_points(robot: Robot, reach: Reach, kin: _Kinematics | None, what: str) -> None:
    """``link_points`` of a reachable answer: an empty array (the robot does not say), or [L, 3] finite
    points starting at the base and passing within ``FK_POSITION_M`` of the flange (by ``kin``)."""
    who = _who(robot)
    pts = robot.link_points(tuple(reach.joints or ()))
    if not (isinstance(pts, np.ndarray) and pts.ndim == 2 and pts.shape[1] == 3 and np.all(np.isfinite(pts))):
        got = f"{pts.dtype} {pts.shape}" if isinstance(pts, np.ndarray) else type(pts).__name__
        _fail(f"{who}: {what}: link_points must return a finite [L, 3] array, got {got}")
    if len(pts) == 0:
        return
    base = robot.model().base_pose[:3, 3]
    if np.linalg.norm(pts[0] - base) > FK_POSITION_M:
        _fail(f"{who}: {what}: link_points must start at the base {base.round(3).tolist()}, starts at "
              f"{pts[0].round(3).tolist()}")
    if kin is not None:
        flange = kin.flange_pose(tuple(reach.joints or ()))[:3, 3]
        if np.linalg.norm(pts - flange, axis=1).min() > FK_POSITION_M:
            _fail(f"{who}: {what}: link_points does not pass the flange at {flange.round(3).tolist()} "
                  "(forward kinematics of the URDF)")


# ------------------------------------------------------------------------------------------- suite
def robot_conformance(factory: Callable[[], Robot] | str, shelf: ShelfSpec | None = None,
                      viewpoints: NDArray[np.float64] | None = None, samples: int = 6) -> RobotReport:
    """Run every robot check on a fresh robot from ``factory`` (a class, a callable, or a registered name),
    for ``shelf`` (default ``ShelfSpec()``) and ``viewpoints`` [V, 4, 4] (default: the default viewpoint
    set). ``samples`` reachable and as many unreachable views are verified one by one."""

    def build(name: str) -> Robot:
        from msmem_core.plugins import get_plugin_manager

        out: Robot = get_plugin_manager().build("robot", name)
        return out

    robot: Robot = built(factory, Robot, "robot_conformance", "a Robot factory (a class, a callable or a "
                         "registered name)", build)
    shelf = shelf or ShelfSpec()
    views = (generate_viewpoints(ViewpointConfig(), shelf) if viewpoints is None
             else np.asarray(viewpoints, dtype=np.float64))
    if views.ndim != 3 or views.shape[1:] != (4, 4):
        raise ConformanceUsageError(f"robot_conformance expects viewpoints of shape [V, 4, 4], got {views.shape}")
    try:
        return _run(robot, shelf, views, samples)
    finally:
        robot.close()


def _run(robot: Robot, shelf: ShelfSpec, views: NDArray[np.float64], samples: int) -> RobotReport:
    who = _who(robot)
    m = check_model(robot)
    check_mounts(robot)
    mask = robot.reachable_views(views, shelf)
    if not (isinstance(mask, np.ndarray) and mask.dtype == bool and mask.shape == (len(views),)):
        got = f"{mask.dtype} {mask.shape}" if isinstance(mask, np.ndarray) else type(mask).__name__
        _fail(f"{who}: reachable_views must return a bool array of shape ({len(views)},), got {got}")
    again = robot.reachable_views(views, shelf)
    if not np.array_equal(mask, again):
        _fail(f"{who}: reachable_views gave two different answers for the same views and shelf "
              f"({int(mask.sum())} vs {int(np.asarray(again).sum())} reachable)")
    n_reach = int(mask.sum())
    if not robot.arm:
        if n_reach != len(views):
            _fail(f"{who}: a robot without an arm (arm = False) must reach every view; it reaches {n_reach} of "
                  f"{len(views)}")
        return RobotReport(m.name, False, len(views), n_reach, 0)
    if n_reach == 0:
        _fail(f"{who}: reaches none of the {len(views)} views: check its base pose and its camera mount")
    kin = _Kinematics(m, shelf)
    try:
        checked = _verify(robot, shelf, views, mask, samples, kin)
    finally:
        kin.close()
    return RobotReport(m.name, True, len(views), n_reach, checked)


def _spread(idx: NDArray[np.int64], k: int) -> NDArray[np.int64]:
    return idx[np.unique(np.linspace(0, len(idx) - 1, min(k, len(idx))).round().astype(int))] if len(idx) else idx


def _verify(robot: Robot, shelf: ShelfSpec, views: NDArray[np.float64], mask: NDArray[np.bool_], samples: int,
            kin: _Kinematics) -> int:
    who, m = _who(robot), robot.model()
    mount_inv = np.linalg.inv(robot.camera_mount())
    checked = 0
    for v in _spread(np.flatnonzero(mask), samples):
        r = robot.reach_camera(views[v], shelf)
        if not r.reachable:
            _fail(f"{who}: reachable_views says view {v} is reachable, reach_camera says not ({r.reason})")
        check_answer(robot, r, views[v] @ mount_inv, shelf, f"view {v}", kin)
        check_link_points(robot, r, kin, f"view {v}")
        if robot.reach_camera(views[v], shelf) != r:
            _fail(f"{who}: view {v}: two ik calls for the same pose gave different answers")
        checked += 1
    for v in _spread(np.flatnonzero(~mask), samples):
        check_refusal(robot.reach_camera(views[v], shelf), who,
                      f"view {v} (reachable_views says it is not reachable)")
    base = m.base_pose
    far = base.copy()
    far[:3, 3] = base[:3, 3] + np.array([0.0, 0.0, FAR_M])
    check_refusal(robot.ik(far, shelf), who, f"a flange pose {FAR_M:g} m above the base")
    first = int(np.flatnonzero(mask)[0])
    inside = views[first] @ mount_inv
    inside = inside.copy()
    centre, _ = shelf.boards()[0]  # the bottom board
    inside[:3, 3] = centre
    check_refusal(robot.ik(inside, shelf), who, "a flange pose inside the shelf's bottom board")
    # paths: standing still at a reachable pose is a path; one that leaves for a far point is not
    tool = views[first] @ mount_inv @ robot.tool_mount()
    r = robot.reach_path(np.stack([tool, tool]), shelf)
    if not r.reachable:
        _fail(f"{who}: reach_path refuses a path that stays at reachable view {first}'s pose: {r.reason}")
    check_answer(robot, r, tool @ np.linalg.inv(robot.tool_mount()), shelf, f"the path at view {first}", kin)
    away = tool.copy()
    away[:3, 3] = tool[:3, 3] + np.array([0.0, 0.0, FAR_M])
    r = robot.reach_path(np.stack([tool, away]), shelf)
    check_refusal(r, who, f"a path from view {first}'s pose to {FAR_M:g} m above it")
    if "path point" not in r.reason:
        _fail(f"{who}: a refused path's reason must name the path point that failed ('path point k of n: ...'), "
              f"got {r.reason!r}")
    return checked


__all__ = ["RobotReport", "check_answer", "check_link_points", "check_model", "check_mounts", "check_refusal",
           "robot_conformance"]
