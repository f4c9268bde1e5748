"""Robots (docs/explanation/robots.md): the plugin kind, the Panda's IK and collision checks (real pybullet, no mocks),
the reachable views and their cache, the config reference, and the view skill and IG term respecting
what the robot reaches."""

from __future__ import annotations

import json

import numpy as np
import pytest
from msmem_objectives.ig import IGTerm
from msmem_robots import reach
from msmem_robots.config import PandaConfig
from msmem_robots.floating import FloatingRobot
from msmem_robots.panda import PandaRobot
from msmem_view.skill import ViewSkill
from typer.testing import CliRunner

from msmem_core.cli import build_app
from msmem_core.config import RunConfig, load_config
from msmem_core.errors import PluginError
from msmem_core.interfaces import CandidateBatch, DecisionContext, Reach, Robot, RobotModel, Workspace
from msmem_core.plugins.manager import ComponentRef
from msmem_core.run.runner import check_components
from msmem_core.testing.builders import decision_context, default_workspace
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

SHELF = ShelfSpec()
VIEWS = generate_viewpoints(ViewpointConfig(), SHELF)
INTO_SHELF = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Flange orientation pointing into the shelf (+y), its x along the shelf."""


def flange(position: tuple[float, float, float]) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = INTO_SHELF, position
    return t


@pytest.fixture(scope="module")
def panda() -> PandaRobot:
    robot = PandaRobot(PandaConfig(disk_cache=False))
    yield robot
    robot.close()


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("MSMEM_CACHE_DIR", str(tmp_path))
    reach.clear_memory()
    yield tmp_path / "reach"
    reach.clear_memory()


def test_both_robots_register_as_a_plugin_kind(plugin_manager):
    robots = plugin_manager.robots()
    assert {"floating", "panda"} <= set(robots)
    assert robots["panda"].kind == "robot"
    assert robots["panda"].config_model is PandaConfig
    assert {r["name"] for r in plugin_manager.listing() if r["kind"] == "robot"} >= {"floating", "panda"}
    assert isinstance(plugin_manager.build("robot", "panda"), PandaRobot)
    assert RunConfig().robot.name == "floating"


def test_panda_reaches_a_pose_in_front_of_it_and_refuses_one_3m_away(panda):
    model = panda.model()
    assert isinstance(model, RobotModel)
    assert model.urdf is not None
    assert model.urdf.endswith("franka_panda/panda.urdf")
    assert len(model.joint_names) == 7
    assert all(lo < hi for lo, hi in zip(model.joint_lower, model.joint_upper, strict=False))
    base = model.base_pose[:3, 3]
    near = flange((base[0], base[1] + 0.45, base[2] + 0.45))  # 45 cm in front of the base, 45 cm up
    got = panda.ik(near, SHELF)
    assert got.reachable, got.reason
    assert got.position_error_m <= 0.005
    assert got.orientation_error_deg <= 2.0
    q = np.array(got.joints)
    assert np.all(q >= np.array(model.joint_lower) - 1e-9)
    assert np.all(q <= np.array(model.joint_upper) + 1e-9)
    fk = panda.flange_pose(q)  # forward kinematics of the answer, independently of ik's own check
    assert np.linalg.norm(fk[:3, 3] - near[:3, 3]) <= 0.005
    assert np.degrees(np.arccos(np.clip((np.trace(fk[:3, :3].T @ near[:3, :3]) - 1) / 2, -1, 1))) <= 2.0
    assert panda.collisions(q, SHELF) == []

    far = flange((base[0], base[1] + 3.0, base[2] + 0.45))
    miss = panda.ik(far, SHELF)
    assert not miss.reachable
    assert miss.joints is None
    assert miss.position_error_m > 1.5
    assert "no IK answer" in miss.reason


def test_a_configuration_inside_a_shelf_board_collides(panda):
    # leaning into the shelf (default base): by joint 2 the hand ends in the top board, between the boards
    # (3 cm from the nearest, clear at the default 1 cm margin) or in the bottom board
    lean = lambda q2: (0.0, q2, 0.0, -1.2, 0.0, 3.0, 0.785)  # noqa: E731
    assert 0.2 < panda.flange_pose(lean(0.8))[1, 3] < SHELF.depth_m  # the flange is inside the shelf
    assert panda.collisions(lean(0.8), SHELF) == []
    top, bottom = panda.collisions(lean(0.6), SHELF), panda.collisions(lean(1.0), SHELF)
    assert "panda_hand-top" in top, top
    assert not any(h.endswith("-bottom") for h in top), top
    assert "panda_hand-bottom" in bottom, bottom
    assert not any(h.endswith("-top") for h in bottom), bottom
    wide = PandaRobot(PandaConfig(collision_margin_m=0.1, disk_cache=False))  # the margin counts
    try:
        assert any(h.endswith("-bottom") for h in wide.collisions(lean(0.8), SHELF))
    finally:
        wide.close()


def test_a_configuration_folded_onto_itself_collides_unless_self_collision_is_off(panda):
    # joint 4 near its lower limit folds the forearm back: link 7 and the hand end against link 1
    folded = (-0.29, 1.09, -1.6, -2.98, -0.57, 0.69, -2.43)
    hits = panda.collisions(folded, SHELF)
    assert "panda_link1-panda_hand" in hits, hits
    assert all("-panda_" in h for h in hits), hits  # only the arm's own links: the shelf is far
    assert panda.collisions(panda.model().home, SHELF) == []
    loose = PandaRobot(PandaConfig(self_collision=False, disk_cache=False))
    try:
        assert loose.collisions(folded, SHELF) == []
    finally:
        loose.close()


def test_the_wrist_cameras_body_collides_and_may_not_sit_in_the_hand():
    lean = (0.0, 0.8, 0.0, -1.2, 0.0, 3.0, 0.785)  # the flange inside the shelf, every link clear of the boards
    far = dict(camera_offset_m=(-0.1, 0.1, 0.03), disk_cache=False)  # the camera 14 cm off the flange axis
    out, bodiless = PandaRobot(PandaConfig(**far)), PandaRobot(PandaConfig(**far, camera_box_m=None))
    try:
        assert out.collisions(lean, SHELF) == ["camera-bottom"]  # only the camera touches
        assert bodiless.collisions(lean, SHELF) == []
    finally:
        out.close()
        bodiless.close()
    # a camera mount 6 cm along the flange's y puts the camera's body 25 mm into the hand: refused, naming the fields
    inside = PandaRobot(PandaConfig(camera_offset_m=(0.0, 0.06, 0.03), camera_rpy_deg=(0.0, 0.0, 0.0),
                                    disk_cache=False))
    with pytest.raises(PluginError, match=r"camera_offset_m \(0.0, 0.06, 0.03\).*into panda_hand \(25 mm\)"):
        inside.collisions(lean, SHELF)
    assert PandaRobot(PandaConfig(camera_offset_m=(0.0, 0.06, 0.03), camera_box_m=None,
                                  disk_cache=False)).collisions(lean, SHELF) == []


def test_ik_refuses_a_pose_it_reaches_only_through_a_board(panda):
    # inside the top board, 5 cm into the shelf: kinematically easy, but the hand is in the board
    inside_top = flange((0.0, 0.05, SHELF.height_m + SHELF.wall_m / 2))
    got = panda.ik(inside_top, SHELF)
    assert not got.reachable
    assert any(h.endswith("-top") for h in got.collisions), got
    assert "collides" in got.reason


def test_reachable_view_count_is_between_1_and_300_and_deterministic(cache_dir):
    first = PandaRobot(PandaConfig())
    mask = first.reachable_views(VIEWS, SHELF)
    assert first.last_reach is not None
    assert first.last_reach.source == "computed"
    assert mask.shape == (300,)
    assert mask.dtype == bool
    assert 1 <= mask.sum() < 300
    assert first.reach_camera(VIEWS[155], SHELF).reachable == mask[155]  # the default start view
    # cached: the same answer from memory, then from disk for a new process (memory cleared)
    assert np.array_equal(first.reachable_views(VIEWS, SHELF), mask)
    assert first.last_reach.source == "memory"
    assert len(list(cache_dir.glob("panda-*.npy"))) == 1
    reach.clear_memory()
    assert np.array_equal(first.reachable_views(VIEWS, SHELF), mask)
    assert first.last_reach.source == "disk"
    first.close()
    # computed again from scratch by another robot: the same views
    again = PandaRobot(PandaConfig(disk_cache=False))
    assert np.array_equal(Robot.reachable_views(again, VIEWS, SHELF), mask)  # the uncached computation
    # another viewpoint set, another base: other cache entries
    assert again.reachable_views(VIEWS[:10], SHELF).shape == (10,)
    assert again.last_reach.source == "computed"
    moved = PandaRobot(PandaConfig(base_position_m=(0.0, -0.75, -0.3), disk_cache=False))
    moved.reachable_views(VIEWS[:10], SHELF)
    assert moved.last_reach is not None
    assert moved.last_reach.source == "computed"
    again.close()
    moved.close()


def test_robot_reach_command_reports_the_count(cache_dir):
    out = CliRunner().invoke(build_app(), ["robot", "reach", "--json"])
    assert out.exit_code == 0, out.output
    got = json.loads(out.output)
    assert got["robot"] == "panda"
    assert got["views"] == 300
    assert got["reachable"] == len(got["reachable_views"])
    assert 1 <= got["reachable"] < 300
    text = CliRunner().invoke(build_app(), ["robot", "reach", "--robot", "floating"])
    assert text.exit_code == 0
    assert "robot floating: 300 of 300 viewpoints reachable" in text.output


@pytest.mark.parametrize(("robot", "message"), [
    ({"name": "ur5"}, "no robot named 'ur5'; available: floating, panda"),
    ({"name": "panda", "params": {"base_position_m": [0.0, -0.5]}}, "robot 'panda': robot.params.base_position_m"),
    ({"name": "panda", "params": {"base_yaw_deg": 400}}, "robot 'panda': robot.params.base_yaw_deg"),
    ({"name": "panda", "params": {"gripper_colour": "red"}}, "robot 'panda': robot.params.gripper_colour"),
])
def test_config_errors_name_the_field(plugin_manager, robot, message):
    cfg = load_config("view-only", None, {"robot": robot})
    with pytest.raises(PluginError) as err:
        check_components(cfg, plugin_manager)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_config_names_the_robot(plugin_manager):
    cfg = load_config("view-only", None, {"robot": {"name": "panda", "params": {"base_position_m": [0, -0.6, -0.3]}}})
    assert cfg.robot.name == "panda"
    check_components(cfg, plugin_manager)  # accepted
    robot = plugin_manager.build("robot", cfg.robot, where="robot")
    assert robot.model().base_pose[:3, 3].tolist() == pytest.approx([0.0, -0.6, -0.3])


def test_floating_robot_allows_everything():
    robot = FloatingRobot()
    assert robot.reachable_views(VIEWS, SHELF).all()
    assert robot.ik(flange((0.0, 3.0, 0.1)), SHELF).reachable  # 3 m away: no arm, no limit
    assert robot.reach_camera(VIEWS[0], SHELF).reachable
    assert robot.collisions((), SHELF) == []
    assert robot.model().urdf is None
    ws = Workspace(default_workspace().grid, SHELF)
    with_floating, without = (_view_ctx(Workspace(ws.grid, SHELF, robot=r), visited={3, 155}) for r in (robot, None))
    assert [a.view for a in ViewSkill().propose(with_floating)] == [a.view for a in ViewSkill().propose(without)]
    assert len(ViewSkill().propose(with_floating)) == 298


def _view_ctx(ws: Workspace, visited: set[int]) -> DecisionContext:
    base = decision_context(workspace=ws)
    return DecisionContext(1, base.belief, base.ig, VIEWS, visited, ws, np.random.default_rng(0), True, 0.5)


def test_view_skill_proposes_only_reachable_views(cache_dir):
    robot = PandaRobot(PandaConfig(disk_cache=False))
    ws = Workspace(default_workspace().grid, SHELF, robot=robot)
    mask = robot.reachable_views(VIEWS, SHELF)
    visited = {int(np.flatnonzero(mask)[0]), int(np.flatnonzero(~mask)[0])}
    proposed = [a.view for a in ViewSkill().propose(_view_ctx(ws, visited))]
    assert proposed == [v for v in range(300) if mask[v] and v not in visited]
    robot.close()


class _Reaches(FloatingRobot):
    """A robot that reaches only the views in ``views`` (the IG term's test)."""

    def __init__(self, views: set[int]) -> None:
        super().__init__()
        self.views = views

    def reachable_views(self, viewpoints, shelf):
        return np.array([v in self.views for v in range(len(viewpoints))])

    def ik(self, flange_pose, shelf) -> Reach:
        return Reach(False, reason="test robot")


def test_ig_term_looks_ahead_among_reachable_views_only():
    free = decision_context(visited={0})
    ig = free.ig.view_ig(free.field)
    order = [int(v) for v in np.argsort(-ig) if v != 0]
    _best, runner_up = order[0], order[1]
    ws = free.workspace
    bound = Workspace(ws.grid, ws.shelf, ws.gripper, ws.num_classes, _Reaches(set(order[1:])))
    ctx = decision_context(free.belief, workspace=bound, ig=free.ig, visited={0})
    views = np.array(order[1:], dtype=np.int64)
    scores = IGTerm().score(ctx, CandidateBatch("view", "perception", [], view_indices=views))
    # the best reachable view gets the two-step bonus (the unreachable best view is no candidate)
    assert scores[0] > ig[runner_up] + 1e-9
    assert np.allclose(scores[1:], ig[views[1:]])


def test_an_episode_carries_its_robot_and_refuses_a_start_view_out_of_reach(plugin_manager):
    from msmem_core.errors import UserError
    from msmem_core.run.runner import build_episode
    from msmem_core.testing.builders import conformance_scene

    scene = conformance_scene()
    ep = build_episode(load_config("view-only", None, {"robot": {"name": "panda"}}), plugin_manager, scene=scene)
    assert isinstance(ep.workspace.robot, PandaRobot)
    assert isinstance(build_episode(load_config("view-only"), plugin_manager, scene=scene).workspace.robot,
                      FloatingRobot)
    low = 104  # middle grid, lowest row: the camera right in front of the base, looking up
    cfg = load_config("view-only", None, {"robot": {"name": "panda"}, "msas": {"start_view": low}})
    with pytest.raises(UserError, match=r"robot 'panda' cannot reach msas.start_view \(104\): no IK answer"):
        build_episode(cfg, plugin_manager, scene=scene)


def test_bench_fingerprints_ignore_the_default_robot_only():
    from msmem_core.run.bench import fingerprint, sha256_text
    from msmem_core.testing.builders import conformance_scene

    scene = conformance_scene()
    default = load_config("view-only")
    before_robots = json.dumps(default.model_dump(mode="json", exclude={"threads", "robot", "class_map"}),
                               sort_keys=True)
    assert fingerprint(default, "s", scene, {})["config_sha256"] == sha256_text(before_robots)  # old results match
    panda = load_config("view-only", None, {"robot": {"name": "panda"}})
    assert fingerprint(panda, "s", scene, {})["config_sha256"] != fingerprint(default, "s", scene, {})["config_sha256"]


# ------------------------------------------------------------------- tool paths of pushes and grasps
def test_densify_spaces_path_points_and_keeps_each_segments_end_orientation():
    from scipy.spatial.transform import Rotation

    from msmem_core.interfaces import densify

    a, b, c = np.eye(4), np.eye(4), np.eye(4)
    b[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    b[:3, 3] = (0.05, 0.0, 0.0)
    c[:3, 3] = (0.05, 0.01, 0.0)
    out = densify(np.stack([a, b, c]), 0.02)
    assert len(out) == 1 + 3 + 1  # 5 cm in three steps of at most 2 cm, then 1 cm in one
    assert np.array_equal(out[0], a)
    assert np.array_equal(out[3], b)
    assert np.array_equal(out[-1], c)
    gaps = np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1)
    assert gaps.max() <= 0.02 + 1e-12
    assert np.allclose(out[1:4, :3, :3], b[:3, :3])  # inserted points: the segment end's orientation
    assert np.allclose(out[1, :3, 3], (0.05 / 3, 0.0, 0.0))
    assert len(densify(np.stack([a]), 0.02)) == 1


def test_panda_gripper_frame_sits_at_the_fingertips_closing_between_the_fingers(panda):
    q = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
    g = panda.flange_pose(q) @ panda.tool_mount()
    c = panda._client
    names = {n: j for j, n in panda._links.items()}
    left, right = (np.array(c.getLinkState(panda._body, names[f"panda_{s}finger"])[4]) for s in ("left", "right"))
    across = (left - right) / np.linalg.norm(left - right)
    assert abs(float(across @ g[:3, 0])) > 0.999  # the gripper frame's x is the closing direction
    # the finger joints sit 0.0584 m out of the hand, 0.0536 m behind the fingertips along the approach
    assert np.allclose((left + right) / 2, g[:3, 3] - 0.0536 * g[:3, 2], atol=1e-3)


def test_floating_robot_follows_any_tool_path():
    far = np.stack([flange((0.0, 3.0, 0.1)), flange((2.0, -3.0, 0.1))])
    assert not FloatingRobot.arm
    assert PandaRobot.arm
    assert FloatingRobot().reach_path(far, SHELF).reachable


def test_panda_follows_a_path_in_front_of_it_and_refuses_a_top_down_push_inside_the_shelf(panda):
    from msmem_push.skill import PushAction, PushConfig, PushSkill

    base = panda.model().base_pose[:3, 3]
    inv_mount = np.linalg.inv(panda.tool_mount())
    free = np.stack([flange((base[0] + dx, base[1] + 0.45, base[2] + 0.45)) @ panda.tool_mount() for dx in (0, 0.1)])
    got = panda.reach_path(free, SHELF)
    assert got.reachable, got.reason
    fk = panda.flange_pose(got.joints) @ panda.tool_mount()  # the answer is at the path's end
    assert np.linalg.norm(fk[:3, 3] - free[-1][:3, 3]) <= 0.005
    away = np.stack([free[0], flange((0.0, 3.0, 0.45)) @ panda.tool_mount()])
    miss = panda.reach_path(away, SHELF)
    assert not miss.reachable
    from msmem_core.interfaces import densify

    n = len(densify(away, 0.02))
    k = int(miss.reason.split()[2])
    assert 0 < k < n  # the start is reached, a later point is not
    assert miss.reason.startswith(f"path point {k} of {n}: ")
    # the floating gripper's push: hand pointing down, 2 cm above the floor, into the 28 cm shelf
    push = PushSkill(PushConfig()).waypoints(PushAction(start_m=(0.0, 0.05), direction=(0.0, 1.0), length_m=0.1,
                                                         height_m=0.02))
    assert np.allclose(push[1][:3, 2], (0, 0, -1))
    no = panda.reach_path(push, SHELF)
    assert not no.reachable
    assert "collides with the shelf" in no.reason, no.reason
    assert "-top" in no.reason, no.reason
    assert panda.ik(push[0] @ inv_mount, SHELF).reachable  # in front of the shelf it reaches the pose


class _LeftOnly(FloatingRobot):
    """An arm that follows only tool paths whose second point lies at x < 0 (counting its checks)."""

    arm = True
    side = -1.0

    def __init__(self) -> None:
        super().__init__()
        self.asked = 0

    def reach_path(self, tool_poses, shelf, step_m=0.02) -> Reach:
        self.asked += 1
        return Reach(bool(self.side * tool_poses[1][0, 3] > 0), ())


class _RightOnly(_LeftOnly):
    side = 1.0


class _Nowhere(_LeftOnly):
    side = 0.0


def test_decide_chooses_as_if_the_manipulations_the_robot_cannot_follow_were_never_proposed():
    """Checking only the candidates that could win gives the decision of filtering them all first: the
    same skill, action and value as the floating gripper choosing among the reachable pushes alone, for
    robots that follow the left, the right or no pushes, with and without views competing; the step
    counts what it checked and what failed, and asks the robot no more than that."""
    from msmem_push.effect import AnalyticPushEffect
    from msmem_push.skill import PushAction, PushConfig, PushSkill

    from msmem_core.testing.builders import belief_with_boxes, one_decision

    pushes = [PushAction(start_m=(x, 0.05), direction=(0.0, 1.0), length_m=0.1, height_m=0.02)
              for x in (-0.2, -0.1, 0.1, 0.2, 0.3)]

    class Fixed(PushSkill):
        def __init__(self, only: list[PushAction]) -> None:
            super().__init__(PushConfig())
            self.only = only

        def propose(self, ctx):
            return list(self.only)

    ws = default_workspace()
    floating = Workspace(ws.grid, ws.shelf, ws.gripper, ws.num_classes, FloatingRobot())
    belief = belief_with_boxes(ws.grid, [((-0.25, 0.1, 0.0), (0.25, 0.2, 0.1), 3)], free="none")
    chosen = set()
    for robot in (_LeftOnly(), _RightOnly(), _Nowhere()):
        follows = [p for p in pushes if robot.side * p.start_m[0] > 0]
        bound = Workspace(ws.grid, ws.shelf, ws.gripper, ws.num_classes, robot)
        for views in ([("view", ViewSkill())], []):
            robot.asked = 0
            if not follows and not views:
                with pytest.raises(RuntimeError, match="no skill proposed"):
                    one_decision([("push", Fixed(pushes), AnalyticPushEffect())], belief, workspace=bound)
                continue
            d = one_decision([*views, ("push", Fixed(pushes), AnalyticPushEffect())], belief, workspace=bound)
            ref = one_decision([*views, ("push", Fixed(follows), AnalyticPushEffect())], belief, workspace=floating)
            assert d.skill.name == ref.skill.name
            assert d.action == ref.action
            assert d.value == pytest.approx(ref.value)
            assert d.candidates["push"] == len(pushes)
            assert d.unreachable["push"] <= d.reach_checked["push"] == robot.asked <= len(pushes)
            assert ref.reach_checked == {}  # the floating gripper checks nothing
            chosen.add((d.skill.name, d.action.start_m[0] if d.skill.name == "push" else None))
            if not views:  # the pushes compete only with each other: the best is always checked
                assert d.reach_checked["push"] >= 1
    assert len({c for c in chosen if c[0] == "push"}) >= 2, chosen  # the robots' pushes differ
    # before its first check, the decision gives the robot the belief's occupied space, once
    robot = _LeftOnly()
    seen: list[np.ndarray] = []
    robot.use_obstacles = seen.append  # type: ignore[method-assign]
    one_decision([("push", Fixed(pushes), AnalyticPushEffect())], belief,
                 workspace=Workspace(ws.grid, ws.shelf, ws.gripper, ws.num_classes, robot))
    assert robot.asked >= 1
    assert len(seen) == 1
    np.testing.assert_array_equal(seen[0], ws.grid.column_boxes(belief.expected_occupancy() > 0.5))
    assert len(seen[0]) > 0


def test_each_step_records_the_arm_configuration_that_reaches_its_view_and_the_report_draws_it(
        plugin_manager, tmp_path):
    """With the Panda, a view's step record holds the IK answer for its camera pose: forward kinematics
    of those joints (computed here, in a robot of its own) puts the wrist camera at the chosen view, and
    the drawn points run from the base to the fingertips. The report draws the arm; without an arm there
    is no record."""
    from msmem_core.run.report import arm_at, write_report
    from msmem_core.run.runfolder import load_run
    from msmem_core.run.runner import build_episode, run_episode
    from msmem_core.testing.builders import conformance_scene
    from msmem_core.world.geometry import rotation_angle_deg

    small = {"camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}, "steps": 3}
    ep = build_episode(load_config("view-only", None, {**small, "robot": {"name": "panda"}}), plugin_manager,
                       scene=conformance_scene())
    run_episode(ep, tmp_path / "run")
    check = PandaRobot(PandaConfig(disk_cache=False))
    try:
        for rec in ep.records:
            arm = rec["arm"]
            assert arm["reachable"], arm
            camera = check.flange_pose(arm["joints"]) @ check.camera_mount()
            view = ep.viewpoints[rec["action"]["view"]]
            assert np.linalg.norm(camera[:3, 3] - view[:3, 3]) < 0.006
            assert rotation_angle_deg(camera, view) < 2.5
            points = np.asarray(arm["points"])
            assert np.allclose(points[0], PandaConfig().base_position_m)
            tip = check.flange_pose(arm["joints"]) @ check.tool_mount()
            assert np.allclose(points[-1], tip[:3, 3], atol=1e-3)
            assert len(points) >= 8
            assert np.linalg.norm(np.diff(points, axis=0), axis=1).max() < 0.45
    finally:
        check.close()
    run = load_run(tmp_path / "run")
    assert arm_at(run, 2)[0] == 2
    write_report(tmp_path / "run", png=False)
    assert "arm (step 2)" in (tmp_path / "run" / "report.html").read_text()
    plain = build_episode(load_config("view-only", None, small), plugin_manager, scene=conformance_scene())
    run_episode(plain)
    assert all("arm" not in rec for rec in plain.records)


@pytest.mark.parametrize("name", ["panda", "ur5e"])
def test_the_links_behind_the_hand_keep_out_of_believed_objects_along_a_path(name, plugin_manager):
    """A forward push path the arm follows; a believed box where one of its links behind the hand ends up
    refuses it (``link-object``), a box around the hand alone does not (the skill's tool checks the hand)."""
    from msmem_push.geometry import gripper_pose

    robot = plugin_manager.build("robot", ComponentRef(name=name), where="robot")
    path = np.stack([gripper_pose((0.25, -0.12), 0.085, (0.0, 1.0), "forward"),
                     gripper_pose((0.25, 0.15), 0.085, (0.0, 1.0), "forward")])
    robot.use_obstacles(None)
    free = robot.reach_path(path, SHELF)
    assert free.reachable, free.reason
    c = robot._client
    robot._set(np.asarray(free.joints))
    boxes = {n: np.array(c.getAABB(robot._body, j)) for j, n in robot._links.items()
             if c.getCollisionShapeData(robot._body, j)}
    exempt = {*robot.camera_carriers, *robot.hand_links}
    nearest = max((n for n in boxes if n not in exempt), key=lambda n: boxes[n][1][1])  # the link nearest the hand
    robot.use_obstacles(boxes[nearest][None])
    blocked = robot.reach_path(path, SHELF)
    assert not blocked.reachable
    assert f"{nearest}-object" in blocked.reason
    assert "believed-occupied space" in blocked.reason
    palm = path[-1][:3, 3] - 0.07 * path[-1][:3, 2]  # 7 cm behind the fingertips: in the hand, the skill's to check
    robot.use_obstacles(np.array([[palm - 0.01, palm + 0.01]]))
    assert robot.reach_path(path, SHELF).reachable
    robot.use_obstacles(None)
    assert robot.reach_path(path, SHELF).reachable


def test_column_boxes_cover_exactly_the_marked_voxels():
    rng = np.random.default_rng(3)
    grid = GridSpec(origin_m=(-0.1, 0.0, 0.0), voxel_m=0.02, shape=(6, 5, 7))
    mask = rng.random(grid.shape) < 0.4
    boxes = grid.column_boxes(mask)
    centres = grid.centers().reshape(-1, 3)
    inside = np.zeros(len(centres), dtype=int)
    for lo, hi in boxes:
        inside += np.all((centres > lo) & (centres < hi), axis=1)
    np.testing.assert_array_equal(inside, mask.ravel().astype(int))  # each marked voxel in exactly one box
    assert len(boxes) < mask.sum()  # runs along z are merged
    assert len(grid.column_boxes(np.zeros(grid.shape, dtype=bool))) == 0
