"""A robot arm of a URDF in pybullet, with a wrist camera on its flange: the base class of ``panda`` and
``ur5e`` (docs/how-to/write-a-robot.md).

Inverse kinematics is pybullet's own (``calculateInverseKinematics``, damped least squares with the
null-space variant that pulls towards a rest pose within the joint limits), run in a DIRECT-mode client
of the robot's own, never the simulator's. pybullet is already a dependency, its IK is in C (about a
millisecond per call here) and the same client answers the collision queries (``getClosestPoints``
against the shelf's boards as boxes), so nothing else is installed or fetched. Its answers are not
trusted as they are: each is clipped to the joint limits and accepted only when forward kinematics puts
the flange within ``position_tolerance_m`` and ``orientation_tolerance_deg`` of the asked pose and no
link comes within ``collision_margin_m`` of a board. docs/explanation/robots.md.
"""

from __future__ import annotations

import functools
import importlib.metadata as md
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import PluginError
from msmem_core.interfaces import Reach, Robot, RobotModel, densify
from msmem_core.util.artifacts import sha256_file
from msmem_core.util.quiet import quiet_stdio

with quiet_stdio():  # pybullet prints its build time on import
    import pybullet
    from pybullet_utils.bullet_client import BulletClient
from msmem_core.world.geometry import matrix_to_quat, pose_matrix, rotation_angle_deg, yaw_quat
from msmem_core.world.scene import ShelfSpec
from msmem_robots.config import ArmConfig
from msmem_robots.reach import ReachInfo, cached_reach, reach_key

BOARDS = ("bottom", "top", "left", "right", "back")
"""Names of ``ShelfSpec.boards()`` in its order."""


@functools.cache
def _library_identity(urdf: Path) -> dict[str, str]:
    return {"urdf_sha256": sha256_file(urdf), "pybullet": md.version("pybullet")}


PATH_IK_ITERATIONS = 20
"""IK iterations per call for a path's next point (``PybulletArm.reach_path``)."""


class PybulletArm(Robot):
    """An arm of a URDF in pybullet with a wrist camera; base in front of the shelf (``ArmConfig``).
    A robot subclasses it with its URDF, joints, links and IK starts (``PandaRobot``, ``UR5eRobot``)."""

    name: ClassVar[str]
    arm_joints: ClassVar[int]
    """The first this many movable joints of the URDF are the arm's (IK solves for them)."""
    flange_link: ClassVar[str]
    """The link IK reaches and the camera and the gripper frame are mounted on."""
    finger_joints: ClassVar[tuple[str, ...]]
    """The hand's joints (prismatic, metres: their sum is the opening)."""
    finger_open: ClassVar[tuple[float, ...]]
    """The positions of the movable joints after the arm's (the hand's), open, in the URDF's order."""
    fingertip_m: ClassVar[float]
    """From the flange along its z to the tips of the open fingers (the gripper frame's origin)."""
    tool_yaw_deg: ClassVar[float] = 0.0
    """The gripper frame's turn about the flange's z (its x: the fingers' closing axis)."""
    camera_carriers: ClassVar[tuple[str, ...]]
    """The links that move rigidly with the wrist camera (and the fingers): a camera mount into them is refused,
    configurations do not check the camera against them."""
    camera_skip: ClassVar[tuple[str, ...]] = ()
    """Other links the camera is not checked against (next to the flange)."""
    hand_links: ClassVar[tuple[str, ...]] = ()
    """Links whose pairs are never checked against each other (a hand's linkage, whose parts touch)."""
    last_link: ClassVar[str]
    """``link_points`` draws the links up to this one."""
    starts: ClassVar[tuple[tuple[float, ...], ...]]
    """Start configurations (and null-space rest poses) of the IK, tried in this order; ``ik_starts`` of them."""

    def urdf(self) -> Path:
        raise NotImplementedError

    def __init__(self, config: ArmConfig) -> None:
        from scipy.spatial.transform import Rotation
        self.config = config
        self._client: Any = None
        self._shelf: ShelfSpec | None = None
        self._boards: list[int] = []
        self.last_reach: ReachInfo | None = None
        """Where the last ``reachable_views`` answer came from and how long it took."""
        c = self.config
        self._base = pose_matrix(c.base_position_m, yaw_quat(np.radians(c.base_yaw_deg)))
        mount = np.eye(4)
        mount[:3, :3] = Rotation.from_euler("xyz", c.camera_rpy_deg, degrees=True).as_matrix()
        mount[:3, 3] = c.camera_offset_m
        self._mount = mount
        self._camera_body: int | None = None
        self._camera_links: list[tuple[int, str]] = []
        """The arm's links a configuration checks the camera against (``self_collision``)."""
        self._camera_centre = np.eye(4)
        """The camera box's centre in the flange frame (behind the optical centre by half its depth)."""
        self._obstacles: NDArray[np.float64] | None = None
        """Believed-occupied boxes [N, 2, 3] that ``reach_path`` keeps the links behind the hand out of."""
        self._obstacle_body: int | None = None
        self._obstacles_built = True
        """Whether ``_obstacle_body`` holds ``_obstacles``."""

    # ------------------------------------------------------------------------------ pybullet client
    def _connect(self) -> Any:
        if self._client is not None:
            return self._client
        with quiet_stdio():  # pybullet prints argv on connecting, and the URDF's missing inertias
            client = BulletClient(connection_mode=pybullet.DIRECT)
            body = client.loadURDF(str(self.urdf()), self.config.base_position_m,
                                   tuple(yaw_quat(np.radians(self.config.base_yaw_deg))), useFixedBase=True)
        names, lower, upper, movable, links = [], [], [], [], {-1: client.getBodyInfo(body)[0].decode()}
        for j in range(client.getNumJoints(body)):
            info = client.getJointInfo(body, j)
            links[j] = info[12].decode()
            if info[2] != pybullet.JOINT_FIXED:
                movable.append(j)
                names.append(info[1].decode())
                lower.append(float(info[8]))
                upper.append(float(info[9]))
        self._body, self._movable, self._links = body, movable, links
        self._self_pairs = self._distant_link_pairs(client, body) if self.config.self_collision else []
        if self.hand_links:
            self._self_pairs = [(i, j) for i, j in self._self_pairs
                                if not (links[i] in self.hand_links and links[j] in self.hand_links)]
        self._flange = next(j for j, n in links.items() if n == self.flange_link)
        self._names = tuple(names[:self.arm_joints])
        self._lower, self._upper = np.array(lower), np.array(upper)
        self._client = client
        if self.config.camera_box_m is not None:
            size = np.asarray(self.config.camera_box_m, dtype=np.float64)
            shape = client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[float(h) for h in size / 2])
            self._camera_body = client.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape,
                                                       basePosition=[0.0, 0.0, 10.0])
            back = np.eye(4)
            back[2, 3] = -size[2] / 2
            self._camera_centre = self._mount @ back
            skip = (*self.camera_carriers, *self.camera_skip)
            self._camera_links = [(j, n) for j, n in links.items()
                                  if n not in skip and client.getCollisionShapeData(body, j)]
            if overlap := self._camera_overlap():
                self.close()
                raise PluginError(
                    f"robot {self.name}: camera_box_m {tuple(self.config.camera_box_m)} at camera_offset_m "
                    f"{tuple(self.config.camera_offset_m)}, camera_rpy_deg {tuple(self.config.camera_rpy_deg)} "
                    f"puts the camera into {overlap}: move it out of the hand (docs/explanation/robots.md)")
        return client

    def _place_camera(self) -> None:
        """Put the camera box where the flange of the current configuration carries it."""
        c = self._client
        state = c.getLinkState(self._body, self._flange, computeForwardKinematics=True)
        pose = pose_matrix(state[4], state[5]) @ self._camera_centre
        c.resetBasePositionAndOrientation(self._camera_body, [float(x) for x in pose[:3, 3]],
                                          [float(x) for x in matrix_to_quat(pose[:3, :3])])

    def _camera_overlap(self) -> str:
        """The links the flange carries that the camera box penetrates (home configuration; they are rigid
        but for the fingers, open here), as ``link (depth mm)``; empty when it clears them all."""
        self._set(np.asarray(self.starts[0]))
        self._place_camera()
        c, out = self._client, []
        for j, name in self._links.items():
            if name in self.camera_carriers:
                depth = min((p[8] for p in c.getClosestPoints(self._camera_body, self._body, 0.0, -1, j)), default=0.0)
                if depth < 0.0:
                    out.append(f"{name} ({-depth * 1000:.0f} mm)")
        return ", ".join(out)

    @staticmethod
    def _distant_link_pairs(client: Any, body: int) -> list[tuple[int, int]]:
        """Pairs of links with collision shapes at least three joints apart along the kinematic tree (the
        ones that can touch only when the arm folds onto itself)."""
        parent = {j: client.getJointInfo(body, j)[16] for j in range(client.getNumJoints(body))}

        def chain(j: int) -> list[int]:
            out = [j]
            while j != -1:
                j = parent[j]
                out.append(j)
            return out

        def apart(i: int, j: int) -> int:
            a, b = chain(i), chain(j)
            common = next(x for x in a if x in b)
            return a.index(common) + b.index(common)

        shaped = [j for j in range(-1, len(parent)) if client.getCollisionShapeData(body, j)]
        return [(i, j) for k, i in enumerate(shaped) for j in shaped[k + 1:] if apart(i, j) >= 3]

    def _set(self, arm: NDArray[np.float64]) -> None:
        c = self._client
        for j, q in zip(self._movable, [*arm, *self.finger_open], strict=True):
            c.resetJointState(self._body, j, float(q))

    def _use_shelf(self, shelf: ShelfSpec) -> None:
        """The shelf's boards as static boxes in the robot's client (rebuilt when the shelf changes)."""
        c = self._connect()
        if shelf == self._shelf:
            return
        for b in self._boards:
            c.removeBody(b)
        self._boards = []
        for centre, half in shelf.boards():
            shape = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[float(h) for h in half])
            self._boards.append(c.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape,
                                                  basePosition=[float(x) for x in centre]))
        self._shelf = shelf

    def close(self) -> None:
        if self._client is not None:
            self._client.disconnect()
            self._client = None
            self._shelf, self._boards, self._camera_body = None, [], None
            self._obstacle_body, self._obstacles_built = None, False

    # ------------------------------------------------------------------------------------ interface
    def model(self) -> RobotModel:
        self._connect()
        return RobotModel(name=self.name, urdf=str(self.urdf()), base_pose=self._base.copy(), joint_names=self._names,
                          joint_lower=tuple(self._lower[:self.arm_joints]),
                          joint_upper=tuple(self._upper[:self.arm_joints]),
                          flange_link=self.flange_link, finger_joints=self.finger_joints, home=self.starts[0])

    def camera_mount(self) -> NDArray[np.float64]:
        return self._mount.copy()

    def tool_mount(self) -> NDArray[np.float64]:
        """The gripper frame at the fingertips: the flange's turned ``tool_yaw_deg`` about its z,
        ``fingertip_m`` out along z."""
        from scipy.spatial.transform import Rotation
        m = np.eye(4)
        m[:3, :3] = Rotation.from_euler("z", self.tool_yaw_deg, degrees=True).as_matrix()
        m[2, 3] = self.fingertip_m
        return m

    def use_obstacles(self, boxes: NDArray[np.float64] | None) -> None:
        """Keep the links behind the hand (all but ``camera_carriers`` and ``hand_links``) out of these boxes
        along ``reach_path`` (one compound body in the robot's client, built when first needed)."""
        self._obstacles = None if boxes is None or not len(boxes) else np.asarray(boxes, dtype=np.float64)
        self._obstacles_built = False

    def _obstacle_hits(self) -> list[str]:
        """``link-object`` for each link behind the hand touching a believed-occupied box."""
        c = self._client
        if not self._obstacles_built:
            if self._obstacle_body is not None:
                c.removeBody(self._obstacle_body)
                self._obstacle_body = None
            if self._obstacles is not None:
                half = (self._obstacles[:, 1] - self._obstacles[:, 0]) / 2
                centre = self._obstacles.mean(axis=1)
                shape = c.createCollisionShapeArray(
                    shapeTypes=[pybullet.GEOM_BOX] * len(half), halfExtents=half.tolist(),
                    collisionFramePositions=centre.tolist())
                self._obstacle_body = c.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape)
            self._obstacles_built = True
        if self._obstacle_body is None:
            return []
        exempt = {*self.camera_carriers, *self.hand_links}
        touching = {p[3] for p in c.getClosestPoints(self._body, self._obstacle_body, 0.0)}
        return [f"{n}-object" for j, n in self._links.items() if j in touching and n not in exempt]

    def reach_path(self, tool_poses: NDArray[np.float64], shelf: ShelfSpec, step_m: float = 0.02) -> Reach:
        """The first point by ``ik`` (every start configuration), each next one by IK from the previous
        answer (a joint-space path: no joint may change by more than ``path_joint_step_rad`` between
        points at most ``step_m`` apart), every configuration checked against the shelf and the links
        behind the hand against believed-occupied space (``use_obstacles``)."""
        poses = densify(np.asarray(tool_poses, dtype=np.float64), step_m)
        inv = np.linalg.inv(self.tool_mount())
        n = len(poses)
        first = self.ik(poses[0] @ inv, shelf)
        if not first.reachable:
            return Reach(False, None, first.position_error_m, first.orientation_error_deg, first.collisions,
                         f"path point 0 of {n}: {first.reason}")
        q = np.asarray(first.joints)
        if touched := self._obstacle_hits():
            return Reach(False, None, first.position_error_m, first.orientation_error_deg, tuple(touched),
                         f"path point 0 of {n}: the arm touches believed-occupied space ({', '.join(touched[:3])})")
        cfg = self.config
        perr, aerr = first.position_error_m, first.orientation_error_deg
        for k in range(1, n):
            target = poses[k] @ inv
            new, perr, aerr = self._solve(target, q, iterations=PATH_IK_ITERATIONS)
            jump = float(np.abs(new - q).max())
            why = ""
            if perr > cfg.position_tolerance_m or aerr > cfg.orientation_tolerance_deg:
                why = (f"no IK answer near the previous point within {cfg.position_tolerance_m * 1000:g} mm and "
                       f"{cfg.orientation_tolerance_deg:g} deg (best: {perr * 1000:.1f} mm, {aerr:.1f} deg)")
            elif jump > cfg.path_joint_step_rad:
                why = f"a joint would jump {jump:.2f} rad (more than {cfg.path_joint_step_rad:g})"
            elif hits := self._hits():
                what = ", ".join(hits[:3])
                return Reach(False, None, perr, aerr, tuple(hits),
                             f"path point {k} of {n}: the arm collides with the shelf or itself ({what})")
            elif touched := self._obstacle_hits():
                return Reach(False, None, perr, aerr, tuple(touched), f"path point {k} of {n}: the arm touches "
                             f"believed-occupied space ({', '.join(touched[:3])})")
            if why:
                return Reach(False, None, perr, aerr, (), f"path point {k} of {n}: {why}")
            q = new
        return Reach(True, tuple(float(x) for x in q), perr, aerr)

    def _solve(self, target: NDArray[np.float64], start: NDArray[np.float64], check_start: bool = True,
               iterations: int | None = None) -> tuple[NDArray[np.float64], float, float]:
        """IK from ``start`` (also the null-space rest pose), up to ``ik_rounds`` calls each from the
        previous answer, stopping once within tolerance (``check_start``: already at ``start``);
        (configuration set in the client, position error, orientation error). ``iterations`` per call
        (default ``ik_iterations``) with as many more calls as keep the same iteration budget: a path's
        next point, 2 cm from an answer, is usually within tolerance after the first few iterations."""
        cfg, c = self.config, self._client
        per_call = min(iterations or cfg.ik_iterations, cfg.ik_iterations)
        rounds = cfg.ik_rounds * max(1, cfg.ik_iterations // per_call)
        pos, orn = [float(x) for x in target[:3, 3]], [float(x) for x in matrix_to_quat(target[:3, :3])]
        lo, hi = self._lower, self._upper
        rest = [*start, *self.finger_open]
        q = np.asarray(start, dtype=np.float64)
        self._set(q)
        perr, aerr = self._error(target) if check_start else (np.inf, np.inf)
        for _ in range(rounds):
            if perr <= cfg.position_tolerance_m and aerr <= cfg.orientation_tolerance_deg:
                break
            sol = c.calculateInverseKinematics(self._body, self._flange, pos, orn, lowerLimits=list(lo),
                                               upperLimits=list(hi), jointRanges=list(hi - lo), restPoses=rest,
                                               maxNumIterations=per_call, residualThreshold=1e-6)
            q = np.clip(np.asarray(sol[:self.arm_joints]), lo[:self.arm_joints], hi[:self.arm_joints])
            self._set(q)
            perr, aerr = self._error(target)
        return q, perr, aerr

    def flange_pose(self, joints: Sequence[float]) -> NDArray[np.float64]:
        """Forward kinematics: the flange's world pose in configuration ``joints``."""
        c = self._connect()
        self._set(np.asarray(joints, dtype=np.float64))
        state = c.getLinkState(self._body, self._flange, computeForwardKinematics=True)
        return pose_matrix(state[4], state[5])

    def link_points(self, joints: Sequence[float]) -> NDArray[np.float64]:
        """The base and the origin of every link from the first to ``last_link``, then the point between
        the fingertips (the gripper frame), by forward kinematics."""
        c = self._connect()
        self._set(np.asarray(joints, dtype=np.float64))
        hand = next(j for j, n in self._links.items() if n == self.last_link)
        states = [c.getLinkState(self._body, j, computeForwardKinematics=True) for j in range(hand + 1)]
        flange = pose_matrix(states[self._flange][4], states[self._flange][5])
        pts = [self._base[:3, 3].copy(), *(np.asarray(st[4]) for st in states), (flange @ self.tool_mount())[:3, 3]]
        out = np.array(pts, dtype=np.float64)
        keep = np.r_[True, np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-6]  # fixed joints repeat a point
        return out[keep]

    def collisions(self, joints: Sequence[float], shelf: ShelfSpec) -> list[str]:
        self._use_shelf(shelf)
        self._set(np.asarray(joints, dtype=np.float64))
        return self._hits()

    def _hits(self) -> list[str]:
        """What the arm in its current configuration touches: ``link-board`` within the collision margin of
        a shelf board, ``link-link`` for two of its own links in contact (``self_collision``), and the
        same for the camera's body (``camera-board``, ``camera-link``; ``camera_box_m``)."""
        c, margin = self._client, self.config.collision_margin_m
        out = []
        for name, board in zip(BOARDS, self._boards, strict=True):
            links = sorted({p[3] for p in c.getClosestPoints(self._body, board, distance=margin) if p[8] < margin})
            out += [f"{self._links[i]}-{name}" for i in links]
        b = self._body
        out += [f"{self._links[i]}-{self._links[j]}" for i, j in self._self_pairs
                if c.getClosestPoints(b, b, 0.0, i, j)]
        if (cam := self._camera_body) is not None:
            self._place_camera()
            out += [f"camera-{name}" for name, board in zip(BOARDS, self._boards, strict=True)
                    if any(p[8] < margin for p in c.getClosestPoints(cam, board, distance=margin))]
            if self.config.self_collision:
                out += [f"camera-{n}" for j, n in self._camera_links if c.getClosestPoints(cam, b, 0.0, -1, j)]
        return out

    def ik(self, flange_pose: NDArray[np.float64], shelf: ShelfSpec) -> Reach:
        cfg = self.config
        self._use_shelf(shelf)
        target = np.asarray(flange_pose, dtype=np.float64)
        tol_m, tol_deg = cfg.position_tolerance_m, cfg.orientation_tolerance_deg
        best, best_score = Reach(False, reason="no IK start configuration"), np.inf
        for start in self.starts[: cfg.ik_starts]:
            q, perr, aerr = self._solve(target, np.array(start), check_start=False)
            reached = perr <= tol_m and aerr <= tol_deg
            hits = self._hits() if reached else []
            if reached and not hits:
                return Reach(True, tuple(float(x) for x in q), perr, aerr)
            score = 0.0 if reached else max(perr / tol_m, aerr / tol_deg)  # colliding answers first
            if score < best_score:
                what = ", ".join(hits[:3])
                why = (f"every IK answer that reaches it collides with the shelf or itself ({what})" if hits
                       else f"no IK answer within {tol_m * 1000:g} mm and {tol_deg:g} deg (best: "
                       f"{perr * 1000:.1f} mm, {aerr:.1f} deg)")
                best, best_score = Reach(False, None, perr, aerr, tuple(hits), why), score
        return best

    def _error(self, target: NDArray[np.float64]) -> tuple[float, float]:
        state = self._client.getLinkState(self._body, self._flange, computeForwardKinematics=True)
        got = pose_matrix(state[4], state[5])
        return float(np.linalg.norm(got[:3, 3] - target[:3, 3])), rotation_angle_deg(got, target)

    # ------------------------------------------------------------------------------------ cached views
    def identity(self) -> dict[str, Any]:
        """What its answers depend on: config (the cache switch aside), URDF content, pybullet's version."""
        return {"robot": self.name, "config": self.config.model_dump(mode="json", exclude={"disk_cache"}),
                **_library_identity(self.urdf())}

    def reachable_views(self, viewpoints: NDArray[np.float64], shelf: ShelfSpec) -> NDArray[np.bool_]:
        """Computed once per shelf and viewpoint set (in memory, and on disk unless ``disk_cache`` is off)."""
        views = np.asarray(viewpoints, dtype=np.float64)
        key = reach_key(self.identity(), views, shelf)
        mask, self.last_reach = cached_reach(key, self.name, lambda: Robot.reachable_views(self, views, shelf),
                                             disk=self.config.disk_cache)
        return mask
