"""Scene generation: reproducible, valid (no overlap, inside the shelf), at the asked occupancy, hard."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError
from scipy.spatial import Delaunay

from msmem_core.errors import UserError
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshes import object_mesh, part_meshes
from msmem_core.world.scene import SceneSpec
from msmem_core.world.scenegen import SceneGenConfig, clear_generated_scenes, footprint_fraction, generate_scene
from msmem_core.world.viewpoints import generate_viewpoints
from msmem_core.world.visibility import object_pixel_counts
from msmem_core.world.voxelize import object_voxels

EASY = SceneGenConfig(require_hard=False)
HARD_SEED = 26  # a seed whose first attempts pass quickly


@pytest.fixture(scope="module")
def easy_scenes() -> list[SceneSpec]:
    return [generate_scene(seed, EASY) for seed in (0, 1, 2)]


@pytest.fixture(scope="module")
def hard_scene() -> SceneSpec:
    return generate_scene(HARD_SEED, SceneGenConfig())


def test_same_seed_gives_the_same_scene_and_other_seeds_differ(easy_scenes: list[SceneSpec]) -> None:
    assert generate_scene(0, EASY) is easy_scenes[0]  # kept per process
    clear_generated_scenes()  # generated again, from scratch
    again = generate_scene(0, EASY)
    assert again is not easy_scenes[0]
    assert again.model_dump_json() == easy_scenes[0].model_dump_json()
    assert len({s.model_dump_json() for s in easy_scenes}) == 3


def test_occupancy_fraction_is_recorded_and_within_range(easy_scenes: list[SceneSpec]) -> None:
    lo, hi = EASY.occupancy_range
    for scene in easy_scenes:
        assert scene.occupancy_fraction is not None
        assert lo <= scene.occupancy_fraction <= hi
        assert footprint_fraction(scene) == pytest.approx(scene.occupancy_fraction, abs=1e-6)
        assert scene.hidden_objects is not None
        assert scene.seed is not None


def test_occupancy_fraction_matches_the_floor_area_of_the_parts(easy_scenes: list[SceneSpec]) -> None:
    """Independent check: union area of the objects' projected meshes, sampled on a 1 mm raster."""
    scene = easy_scenes[0]
    shelf = scene.shelf
    xs = np.arange(-shelf.width_m / 2, shelf.width_m / 2, 0.001) + 0.0005
    ys = np.arange(0.0, shelf.depth_m, 0.001) + 0.0005
    pts = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    covered = np.zeros(len(pts), dtype=bool)
    for obj in scene.objects:
        for part in part_meshes(obj):
            xy = part.vertices[:, :2]
            near = np.all((pts >= xy.min(axis=0)) & (pts <= xy.max(axis=0)), axis=1)
            covered[near] |= Delaunay(xy).find_simplex(pts[near]) >= 0  # inside the convex projection
    assert covered.mean() == pytest.approx(scene.occupancy_fraction, abs=0.01)


def test_objects_neither_overlap_nor_touch(easy_scenes: list[SceneSpec]) -> None:
    """At 2.5 mm no voxel belongs to two objects, and meshes keep at least min_gap_m apart."""
    for scene in easy_scenes:
        grid = GridSpec.around_box(scene.shelf.interior_lower, scene.shelf.interior_upper, 0.0025)
        seen = np.zeros(grid.size, dtype=np.int32)
        for obj in scene.objects:
            seen[object_voxels(obj, grid)] += 1
        assert seen.max() == 1
        manager = trimesh.collision.CollisionManager()
        for obj in scene.objects:
            manager.add_object(str(obj.id), object_mesh(obj))
        assert manager.min_distance_internal() >= EASY.min_gap_m - 1e-6


def test_objects_stand_inside_the_shelf_with_clearance(easy_scenes: list[SceneSpec]) -> None:
    clr = EASY.wall_clearance_m
    for scene in easy_scenes:
        lo = scene.shelf.interior_lower + np.array([clr, clr, 0.0])
        hi = scene.shelf.interior_upper - clr
        for obj in scene.objects:
            b = object_mesh(obj).bounds
            assert np.all(b[0] >= lo - 1e-9), obj
            assert np.all(b[1] <= hi + 1e-9), obj
            assert b[0][2] == pytest.approx(0.0, abs=1e-9)  # standing on the floor


def test_scene_json_round_trip(easy_scenes: list[SceneSpec], tmp_path: object) -> None:
    path = tmp_path / "scene.json"  # type: ignore[operator]
    easy_scenes[1].to_json(path)
    assert SceneSpec.from_json(path) == easy_scenes[1]


def test_hard_scene_hides_more_than_three_objects_by_an_independent_recount(hard_scene: SceneSpec) -> None:
    cfg = SceneGenConfig()
    assert hard_scene.hidden_objects is not None
    assert hard_scene.hidden_objects >= cfg.min_hidden > 3
    views = generate_viewpoints(cfg.viewpoints, hard_scene.shelf)
    ids = [o.id for o in hard_scene.objects]
    counts = object_pixel_counts(hard_scene.objects, ids, hard_scene.shelf, views, cfg.camera, cfg.visibility_stride)
    hidden = [i for i in ids if counts[i] < cfg.min_visible_pixels]
    assert len(hidden) == hard_scene.hidden_objects


def test_invalid_config_names_the_field() -> None:
    with pytest.raises(ValidationError, match="occupancy_range"):
        SceneGenConfig(occupancy_range=(0.5, 0.3))
    with pytest.raises(ValidationError, match="occupancy_range"):
        SceneGenConfig(occupancy_range=(0.3, 0.95))
    with pytest.raises(ValidationError, match="min_gap_m"):
        SceneGenConfig(min_gap_m=-0.01)
    with pytest.raises(ValidationError, match="extra"):
        SceneGenConfig(occupancy=(0.3, 0.4))  # type: ignore[call-arg]


def test_generation_gives_up_with_a_clear_error() -> None:
    cfg = SceneGenConfig(min_hidden=30, max_tries=1)
    with pytest.raises(UserError, match="hardness"):
        generate_scene(0, cfg)
