"""What a grasp carries out of the shelf and what stops it (``GraspSkill._carried`` and ``_lift``):
the grasped object leaves whole, its own believed voxels beyond the fingers and background-class
voxels do not stop it, another believed object in its way does, unless their silhouettes overlap by
no more than a voxel; the whole carried object must fit under the shelf top (lifted less, down to
``min_lift_m``, where the top leaves less room than ``lift_m``, and with ``short_lift_margin_m`` only
around an object narrow enough for the fingers' margin)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from msmem_grasp.planning import Objects, clear_under_top, under_top, way_out, way_out_meets
from msmem_grasp.skill import GraspAction, GraspConfig, GraspSkill

from msmem_core.map.belief import EvidentialMap
from tests.test_grasp import GRID, INTERIOR, MEAT, SUGAR, box_belief, ctx

pytestmark = pytest.mark.usefixtures("one_torch_thread")
FRONT_TARGET = ((-0.02, 0.02), (0.02, 0.11), 0.17, SUGAR)
"""A 17 cm box in the front row (nothing in front of it)."""


def on(belief: EvidentialMap, cls: int = SUGAR, **kw: object) -> list[GraspAction]:
    skill = GraspSkill(GraspConfig(predictor="geometric", **kw))  # type: ignore[arg-type]
    return [g for g in skill.propose(ctx(belief)) if g.target_class == cls]


def background_front_face(belief: EvidentialMap, box: tuple) -> EvidentialMap:
    """``belief`` with the box's front voxel layer still believed occupied but of class background, as
    the default belief has objects' surfaces that rays labelled background."""
    (x0, y0), (x1, _), h, _ = box
    c = GRID.centers()
    face = (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y0 + GRID.voxel_m)
    face &= (c[..., 2] > 0) & (c[..., 2] < h)
    belief.eta[:, face] = 1.0
    belief.eta[0, face] = 21.0
    assert (belief.expected_occupancy()[face] > 0.5).all()
    return belief


def test_an_objects_own_background_class_surface_does_not_stop_it() -> None:
    """The front-row box is grasped although its front face is believed background: the face is no
    other object's (under the rule before, every believed-occupied voxel outside the region the
    fingers close on stopped it, and it could not be lifted over its own face: no grasp at all)."""
    belief = background_front_face(box_belief([FRONT_TARGET]), FRONT_TARGET)
    grasps = on(belief)
    assert grasps
    assert all(abs(g.retreat_m[0][2] - g.pose[2][3] - 0.03) < 1e-9 for g in grasps)  # the minimum lift


def test_a_neighbour_overlapping_the_objects_silhouette_by_one_voxel_column_does_not_stop_it() -> None:
    """A block in front of the target (too tall to lift over with ``max_lift_m`` 5 cm) stops it when it
    overlaps the target's silhouette by two voxel columns, not by one: believed objects reach up to
    a voxel beyond their surfaces, so objects that merely touch overlap by one."""
    target = ((-0.02, 0.18), (0.02, 0.27), 0.10, SUGAR)  # voxel columns x = -0.015 .. 0.015
    one = ((0.01, 0.10), (0.05, 0.16), 0.07, MEAT)  # x = 0.015 .. 0.045: one column in common
    two = ((0.00, 0.10), (0.05, 0.16), 0.07, MEAT)  # x = 0.005 .. 0.045: two
    assert on(box_belief([target, one]), max_lift_m=0.05)
    assert on(box_belief([target, two]), max_lift_m=0.05) == []


# ------------------------------------------------------------------------------ _carried and _lift
def _front_grasp(x: float, y: float, z: float) -> np.ndarray:
    """A grasp from the front (approach +y, closing along x) with its centre at (x, y, z)."""
    pose = np.eye(4)
    pose[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # (b, a x b, a)
    pose[:3, 3] = (x, y, z)
    return pose


def _flat(mask: np.ndarray) -> np.ndarray:
    return np.flatnonzero(mask.reshape(-1))


def test_the_carried_body_is_the_whole_object_and_only_other_objects_are_in_its_way() -> None:
    tall = ((-0.03, 0.15), (0.03, 0.21), 0.24, SUGAR)
    same_in_front = ((-0.03, 0.03), (0.03, 0.09), 0.10, SUGAR)  # its own component, 6 cm in front
    other = ((0.10, 0.03), (0.16, 0.09), 0.10, MEAT)
    belief = box_belief([tall, same_in_front, other])
    c = GRID.centers()
    shell = (np.abs(c[..., 0] - 0.3) < 0.02) & (np.abs(c[..., 1] - 0.05) < 0.02) & (c[..., 2] < 0.1)
    belief.alpha[shell], belief.beta[shell] = 21.0, 1.0  # occupied, class background
    objects = Objects.of(belief, INTERIOR)
    in_tall = (np.abs(c[..., 0]) < 0.03) & (c[..., 1] > 0.15) & (c[..., 1] < 0.21) & (c[..., 2] > 0)
    in_tall &= c[..., 2] < 0.24
    label = int(objects.labels.reshape(-1)[_flat(in_tall)[0]])
    assert label > 0
    region = _flat(in_tall & (c[..., 2] < 0.12))  # what the fingers close on: the lower half
    skill = GraspSkill(GraspConfig(predictor="geometric"))
    body, way = skill._carried(GRID, belief.expected_occupancy(), objects, label, region)
    assert set(_flat(in_tall)) <= set(body)  # its upper half leaves with it
    way3 = way.reshape(GRID.shape)
    in_front = (np.abs(c[..., 0]) < 0.03) & (c[..., 1] > 0.03) & (c[..., 1] < 0.09) & (c[..., 2] > 0)
    in_front &= c[..., 2] < 0.10
    assert way3[in_front].all()  # the other box of its class, 6 cm in front, is in its way
    assert way3[(c[..., 0] > 0.10) & (c[..., 0] < 0.16) & (c[..., 1] > 0.03) & (c[..., 1] < 0.09)
                & (c[..., 2] > 0) & (c[..., 2] < 0.10)].all()  # so is another class's object
    assert not way3[shell].any()  # occupied background-class voxels are no object's
    assert not way3.reshape(-1)[body].any()


def _box_lift(height: float, **kw: object) -> float | None:
    """The lift of a front grasp low (6 cm) on a box of ``height`` standing in the front row."""
    skill = GraspSkill(GraspConfig(predictor="geometric", **kw))  # type: ignore[arg-type]
    c = GRID.centers()
    box = ((-0.03, 0.05), (0.03, 0.11), height, SUGAR)
    belief = box_belief([box])
    objects = Objects.of(belief, INTERIOR)
    inside = (np.abs(c[..., 0]) < 0.03) & (c[..., 1] > 0.05) & (c[..., 1] < 0.11) & (c[..., 2] > 0)
    inside &= c[..., 2] < height
    label = int(objects.labels.reshape(-1)[_flat(inside)[0]])
    region = _flat(inside & (c[..., 2] < 0.12))
    top = float(INTERIOR[5] - skill.config.clearance_m)
    return skill._lift(GRID, belief.expected_occupancy(), objects, label, region, _front_grasp(0.0, 0.05, 0.06),
                       0.06, top)


def test_the_whole_carried_object_must_fit_under_the_shelf_top() -> None:
    """A front grasp low on a box: the fingers close on its lower part only, but the box leaves whole,
    so its top sets the room under the 28 cm shelf top (5 mm clearance). With a 3 cm minimum lift a 20 cm
    box is lifted, a 25 cm one is refused. By default (``min_lift_m`` 0) the 25 cm one is lifted by the
    2 cm the room leaves (whole voxels), a 27 cm one slides out along the floor and one reaching the
    clearance is refused; ``min_lift_m`` 1 cm refuses the 27 cm one."""
    assert _box_lift(0.20, min_lift_m=0.03) == pytest.approx(0.03)
    assert _box_lift(0.25, min_lift_m=0.03) is None
    assert _box_lift(0.25) == pytest.approx(0.02)
    assert _box_lift(0.20, min_lift_m=0.0) == pytest.approx(0.03)
    assert _box_lift(0.25, min_lift_m=0.0) == pytest.approx(0.02)
    assert _box_lift(0.27, min_lift_m=0.0) == pytest.approx(0.0)
    assert _box_lift(0.28, min_lift_m=0.0) is None
    assert _box_lift(0.25, min_lift_m=0.02) == pytest.approx(0.02)
    assert _box_lift(0.27, min_lift_m=0.01) is None


def test_a_short_lift_needs_the_fingers_full_margin_around_the_object() -> None:
    """``short_lift_margin_m``: the 25 cm box (6 cm grasped, the 8 cm gripper) slides out with a 2 cm lift
    when a 2 cm margin is asked, not when 3 cm is; the 20 cm box, lifted the full 3 cm, is not concerned."""
    assert _box_lift(0.25, min_lift_m=0.0, short_lift_margin_m=0.02) == pytest.approx(0.02)
    assert _box_lift(0.25, min_lift_m=0.0, short_lift_margin_m=0.03) is None
    assert _box_lift(0.20, min_lift_m=0.0, short_lift_margin_m=0.03) == pytest.approx(0.03)


def test_an_object_whose_top_the_views_missed_is_as_tall_as_its_class() -> None:
    """The belief shows 12 cm of a box whose class stands 26 cm tall (its top unseen): lifted 3 cm it
    would meet the shelf top, so with a 3 cm minimum lift it is not lifted; by default (``min_lift_m`` 0)
    it leaves with the 1 cm the room allows, not the 3 cm a 12 cm box gets. A 20 cm class is lifted the
    full 3 cm. Without the class's shape the belief's 12 cm is all there is."""
    skill = GraspSkill(GraspConfig(predictor="geometric", min_lift_m=0.03))
    slide = GraspSkill(GraspConfig(predictor="geometric"))
    c = GRID.centers()
    box = ((-0.03, 0.05), (0.03, 0.11), 0.12, SUGAR)
    belief = box_belief([box])
    objects = Objects.of(belief, INTERIOR)
    inside = (np.abs(c[..., 0]) < 0.03) & (c[..., 1] > 0.05) & (c[..., 1] < 0.11) & (c[..., 2] > 0)
    inside &= c[..., 2] < 0.12
    label = int(objects.labels.reshape(-1)[_flat(inside)[0]])
    top = float(INTERIOR[5] - skill.config.clearance_m)
    args = (GRID, belief.expected_occupancy(), objects, label, _flat(inside), _front_grasp(0.0, 0.05, 0.06), 0.06, top)
    assert skill._lift(*args) == pytest.approx(0.03)
    assert skill._lift(*args, extents=(0.10, 0.065, 0.26)) is None
    assert slide._lift(*args, extents=(0.10, 0.065, 0.26)) == pytest.approx(0.01)
    assert skill._lift(*args, extents=(0.10, 0.065, 0.20)) == pytest.approx(0.03)  # a 20 cm one is lifted


def test_another_class_inside_the_objects_own_columns_is_not_in_its_way() -> None:
    """The default belief labels some of a front-row box's own voxels with another class, making
    them a believed object of their own: a full-height column just inside its front face (a column its
    footprint surrounds), or the lower 12 cm of columns whose top is the box's. Nothing else stands
    there: they are not in its way (without the rule either one stops every grasp of the box)."""
    c = GRID.centers()
    inside = (np.abs(c[..., 0]) < 0.01) & (c[..., 1] > 0.03) & (c[..., 1] < 0.04) & (c[..., 2] > 0)
    column = inside & (c[..., 2] < 0.17)
    under = inside & (c[..., 2] < 0.12)
    for band in (column, under):
        belief = box_belief([FRONT_TARGET])
        belief.eta[:, band] = 1.0
        belief.eta[MEAT, band] = 21.0
        objects = Objects.of(belief, INTERIOR)
        assert len(np.unique(objects.labels[band])) == 1
        assert objects.classes[objects.labels[band][0]] == MEAT  # a believed object of its own
        assert on(belief)


@pytest.mark.slow
def test_the_default_belief_of_a_hard_scene_leaves_grasps_of_its_front_row(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``hard25`` scene 0 under the library defaults, 10 views of a grasp-only episode (manipulation held off),
    the grasps as predicted (``turn_to`` empty), the way in tested as every other leg (``move_in_clearance_m``
    None): with a 3 cm lift, the front row's sugar box (17.5 cm) and
    mustard bottle (19 cm) can be grasped from above and carried out; with the lift shrunk to the room under
    the shelf top, the whole front row, and by default all of it but the cracker box. Under the rule before,
    which counted every believed-occupied voxel outside the fingers' region as in the way, it proposed none
    (the boxes' own surface voxels of class background, and their own parts beyond the region, stopped
    them)."""
    from msmem_core.config import load_config
    from msmem_core.map.belief import EvidentialMap as Map
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.bench import suite_scenes
    from msmem_core.run.runner import build_episode, run_episode

    cfg = load_config("grasp-only", None, {"steps": 10, "msas": {"manipulation_window": [999, 999]}})
    ep = build_episode(cfg, get_plugin_manager(), scene=suite_scenes("hard25")[0])
    run_episode(ep, tmp_path)
    skill = next(b.skill for b in ep.skills if b.name == "grasp")
    belief = Map.load(tmp_path / "belief_final.npz")

    def targets(**params: object) -> set[int]:
        """The objects nearest the contacts of the executable grasps, the skill's parameters changed
        (the same fused buffer)."""
        skill.config = skill.config.model_copy(update={"turn_to": (), "move_in_clearance_m": None, **params})
        stages: dict[str, int] = {}
        grasps = skill.executable(belief, ep.scene.shelf, stages, ep.workspace.classes)
        assert grasps, stages
        return {min(ep.scene.objects, key=lambda o: np.hypot(g.contact_m[0] - o.position_m[0],
                                                             g.contact_m[1] - o.position_m[1])).id for g in grasps}

    assert targets(min_lift_m=0.03) <= {1, 4}  # with a 3 cm lift: the sugar box and the mustard bottle
    # where the lift may shrink to the room under the shelf top, the whole front row: also the cracker
    # box and the three 26 cm bleach bottles, which leave held 1 cm above the floor, or along it
    assert targets(min_lift_m=0.0, short_lift_margin_m=None) == {0, 1, 2, 3, 4, 5}
    # by default only where the fingers have their 2 cm margin around the object: not the cracker box,
    # grasped across its 6 cm side or wider
    assert targets(min_lift_m=0.0, short_lift_margin_m=0.02) == {0, 1, 3, 4, 5}
    # (the grasps as predicted, above; the default also turns them to the front and the sides)
    # with a 3 cm lift they add the cracker box, grasped across its 6 cm depth from the side
    assert targets(turn_to=("front", "sides"), min_lift_m=0.03) == {1, 2, 4}
    # the way in tested with the gripper's exact boxes (the default): the cracker box's grasps from above,
    # whose way in passes the shelf top by less than the collision tolerance, are no longer proposed
    assert targets(min_lift_m=0.0, short_lift_margin_m=None, move_in_clearance_m=0.0) == {0, 1, 3, 4, 5}


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 60))
def test_clearing_under_a_bodys_top_in_place_is_the_mask_and_not_its_complement(seed: int, n: int) -> None:
    # the way out of a carried object drops what stands under its top, in its columns and those it surrounds
    rng = np.random.default_rng(seed)
    body = np.unique(rng.integers(0, GRID.size, n))
    if seed % 2:  # a ring of columns around a hole, the hole's column empty
        nz = GRID.shape[2]
        i, j = GRID.shape[0] // 2, GRID.shape[1] // 2
        ring = [((i + di) * GRID.shape[1] + (j + dj)) * nz + 3 for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
        body = np.union1d(body, ring)
    mask = rng.random(GRID.size) < 0.5
    want = mask & ~under_top(GRID, body)
    clear_under_top(GRID, body, mask)
    np.testing.assert_array_equal(mask, want)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 40), st.integers(0, 12))
def test_a_way_out_meets_a_voxel_exactly_when_it_sweeps_it(seed: int, n: int, lift: int) -> None:
    # one masked voxel on the swept path, then one off it: every voxel of the sweep counts, and no other
    rng = np.random.default_rng(seed)
    body = np.unique(rng.integers(0, GRID.size, n))
    path = way_out(GRID, body, lift)[0]
    on = np.zeros(GRID.size, dtype=bool)
    if len(path):
        on[rng.choice(path)] = True
    assert way_out_meets(GRID, body, lift, on) == bool(len(path))
    off = np.zeros(GRID.size, dtype=bool)
    off[rng.choice(np.setdiff1d(np.arange(GRID.size), path))] = True
    assert not way_out_meets(GRID, body, lift, off)


# ------------------------------------------------------------------------------ the fused pass
def _carried_reference(skill: GraspSkill, p: np.ndarray, objects: Objects, label: int, region: np.ndarray,
                       occupied: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``GraspSkill._carried`` (numpy) and the body's sides one voxel in, as ``_lift`` had them."""
    body, way = skill._carried(GRID, p, objects, label, region, occupied)
    stride = GRID.shape[1] * GRID.shape[2]
    return body, way, body[np.isin(body - stride, body) & np.isin(body + stride, body)]


def _random_objects(rng: np.random.Generator) -> tuple[np.ndarray, Objects]:
    """Random occupancy and random components: blobs, rings (a footprint with a hole), objects on the
    floor, at the grid's border and floating, touching one another; ``p`` float32 with values at the
    free threshold."""
    nx, ny, nz = GRID.shape
    labels = np.zeros(GRID.shape, np.int32)
    for lab in range(1, int(rng.integers(2, 7))):
        x0, y0 = int(rng.integers(0, nx - 3)), int(rng.integers(0, ny - 3))
        x1, y1 = min(nx, x0 + int(rng.integers(2, 9))), min(ny, y0 + int(rng.integers(2, 9)))
        z0 = int(rng.integers(0, 4))
        z1 = min(nz, z0 + int(rng.integers(1, 15)))
        block = np.zeros(GRID.shape, bool)
        block[x0:x1, y0:y1, z0:z1] = True
        if rng.random() < 0.4 and x1 - x0 >= 3 and y1 - y0 >= 3:  # a ring
            block[x0 + 1:x1 - 1, y0 + 1:y1 - 1] = False
        labels[block & (rng.random(GRID.shape) < 0.9)] = lab
    p = rng.choice(np.array([0.0, 0.1, 0.3, 0.5, 0.9], np.float32), size=GRID.shape)
    p[labels > 0] = 0.9
    classes = np.arange(labels.max() + 1, dtype=np.int64)
    return p, Objects(labels, classes, labels.astype(np.int64))


def test_the_fused_carried_pass_equals_the_numpy_rules() -> None:
    """``carried_way`` (one numba pass, what ``_lift`` uses) gives ``_carried``'s body and way and the
    body's core, array for array, on random components, regions, margins and occupancy."""
    from msmem_grasp.planning import carried_way

    rng = np.random.default_rng(7)
    compared = 0
    for case in range(60):
        p, objects = _random_objects(rng)
        margin = float(rng.choice([0.0, 0.004, 0.01, 0.02, 0.03]))
        skill = GraspSkill(GraspConfig(predictor="geometric", exit_margin_m=margin))
        occupied = rng.random(GRID.size) < 0.2
        for label in range(1, int(objects.labels.max()) + 1):
            own = objects.voxels_of(label)
            if not len(own):
                continue
            region = own[rng.random(len(own)) < float(rng.choice([0.05, 0.3, 1.0]))]
            want = _carried_reference(skill, p, objects, label, region, occupied)
            got = carried_way(GRID, p, objects, label, region, skill.config.geometric.free_threshold, margin,
                              occupied)
            for name, w, g in zip(("body", "way", "core"), want, got, strict=True):
                assert g.dtype == w.dtype, (case, label, name)
                assert np.array_equal(g, w), (case, label, name)
            compared += 1
    assert compared > 150
    empty = carried_way(GRID, p, objects, 1, np.zeros(0, np.int64), 0.3, 0.02, occupied)
    assert len(empty[0]) == 0
    assert np.array_equal(empty[1], occupied)
    assert empty[1] is not occupied


def test_classes_too_wide_for_the_fingers_are_those_with_every_part_wider_than_the_opening() -> None:
    from msmem_grasp.skill import narrowest_width_m, too_wide

    from msmem_core.world.scene import ObjectClass, Part, object_class

    assert narrowest_width_m(Part(kind="box", size_m=(0.085, 0.09, 0.2))) == pytest.approx(0.085)
    assert narrowest_width_m(Part(kind="cylinder", size_m=(0.043, 0.03))) == pytest.approx(0.086)
    tilted = Part(kind="box", size_m=(0.2, 0.2, 0.2), quat_xyzw=(0.0, 0.3826834, 0.0, 0.9238795))
    assert narrowest_width_m(tilted) is None
    assert narrowest_width_m(Part(kind="convex", vertices_m=((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)))) is None
    wide = {n for n in ("wood_block", "tuna_fish_can", "master_chef_can", "pudding_box", "cracker_box", "mug",
                        "bowl", "sugar_box", "mustard_bottle", "gelatin_box") if too_wide(object_class(n), 0.08)}
    # the mug and the bowl are hollow: their walls are thin parts a rim grasp can span
    assert wide == {"wood_block", "tuna_fish_can", "master_chef_can", "pudding_box"}
    assert not too_wide(object_class("wood_block"), 0.09)  # an 8.5 cm block fits a 9 cm opening
    # one part the fingers can span, or one of unknown width, is enough to keep the class
    block = Part(kind="box", size_m=(0.1, 0.1, 0.1))
    other = block.model_copy(update={"position_m": (0.1, 0.0, 0.0)})
    handle = Part(kind="box", size_m=(0.01, 0.03, 0.05))
    assert too_wide(ObjectClass(name="two_blocks", class_id=1, mass_kg=1.0, parts=(block, other)), 0.08)
    assert not too_wide(ObjectClass(name="block_and_handle", class_id=1, mass_kg=1.0, parts=(block, handle)), 0.08)
    assert not too_wide(ObjectClass(name="block_and_tilt", class_id=1, mass_kg=1.0, parts=(block, tilted)), 0.08)


@pytest.mark.slow
def test_wider_than_opening_skip_drops_the_wood_blocks_grasps_of_a_hard_scene(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``hard25`` scene 13, 16 steps of grasp-only under the library defaults (one thread): after two
    cracker boxes are taken out, the front wood block (8.5 cm wide, the gripper opens 8 cm) has grasp
    candidates; ``wider_than_opening: skip`` drops them and keeps the others."""
    from msmem_core.config import load_config
    from msmem_core.map.belief import EvidentialMap as Map
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.bench import suite_scenes
    from msmem_core.run.runner import build_episode, run_episode

    cfg = load_config("grasp-only", None, {"steps": 16, "threads": 1})
    ep = build_episode(cfg, get_plugin_manager(), scene=suite_scenes("hard25")[13])
    run_episode(ep, tmp_path)
    skill = next(b.skill for b in ep.skills if b.name == "grasp")
    belief = Map.load(tmp_path / "belief_final.npz")
    classes = ep.workspace.classes
    proposed = {}
    for mode in ("keep", "skip"):
        skill.config = skill.config.model_copy(update={"wider_than_opening": mode})
        stages: dict[str, int] = {}
        grasps = skill.executable(belief, ep.scene.shelf, stages, classes)
        proposed[mode] = ({classes[g.target_class - 1].name for g in grasps}, stages["on_object"])
    assert "wood_block" in proposed["keep"][0]
    assert proposed["skip"][0] == proposed["keep"][0] - {"wood_block"}
    assert proposed["skip"][1] < proposed["keep"][1]
