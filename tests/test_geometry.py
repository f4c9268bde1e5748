"""Rigid-body helpers: the oriented-box overlap test (``boxes_overlap``) against its defining properties and
against FCL, and ``ShelfSpec.interior_box``."""

from __future__ import annotations

import fcl
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from msmem_core.world.geometry import boxes_overlap, quat_to_matrix
from msmem_core.world.scene import ShelfSpec

Box = tuple[np.ndarray, np.ndarray, np.ndarray]

coord = st.floats(-0.2, 0.2, allow_nan=False)
half = st.floats(0.002, 0.1, allow_nan=False)
quat = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1)
boxes = st.builds(lambda c, q, h: (np.array(c), quat_to_matrix(q), np.array(h)),
                  st.tuples(coord, coord, coord), quat, st.tuples(half, half, half))


def overlap(a: Box, b: Box, margin: float = 0.0) -> bool:
    """One box against one, through the batched test."""
    return bool(boxes_overlap(a[0][None], a[1][None], a[2][None], b[0], b[1], b[2], margin)[0])


def fcl_collide(a: Box, b: Box, grow: float) -> bool:
    objs = [fcl.CollisionObject(fcl.Box(*(2 * (h + grow))), fcl.Transform(r, c)) for c, r, h in (a, b)]
    return bool(fcl.collide(*objs, fcl.CollisionRequest(), fcl.CollisionResult()))


@settings(max_examples=200, deadline=None)
@given(boxes, boxes)
def test_a_box_overlaps_itself_and_every_box_around_its_centre(a: Box, b: Box) -> None:
    assert overlap(a, a)
    assert overlap(a, (a[0], b[1], b[2]))


@settings(max_examples=300, deadline=None)
@given(boxes, boxes)
def test_the_test_is_symmetric(a: Box, b: Box) -> None:
    """Up to rounding: swapping the boxes changes the answer only for boxes within 1e-9 m of touching."""
    if overlap(a, b):
        assert overlap(b, a, margin=1e-9)
    if overlap(b, a):
        assert overlap(a, b, margin=1e-9)


@settings(max_examples=200, deadline=None)
@given(boxes, boxes, st.tuples(coord, coord, coord).filter(lambda u: np.linalg.norm(u) > 1e-3),
       st.floats(1e-4, 0.1))
def test_boxes_farther_apart_than_their_bounding_spheres_do_not_overlap(a: Box, b: Box, direction, gap: float) -> None:
    u = np.asarray(direction) / np.linalg.norm(direction)
    far = (a[0] + u * (np.linalg.norm(a[2]) + np.linalg.norm(b[2]) + gap), b[1], b[2])
    assert not overlap(a, far)
    assert not overlap(far, a)


@settings(max_examples=400, deadline=None)
@given(boxes, boxes)
def test_the_test_agrees_with_fcl(a: Box, b: Box) -> None:
    """Where FCL is unambiguous (the answer is the same with both boxes 1 um smaller or larger)."""
    b = (a[0] + 0.5 * (b[0] - a[0]), b[1], b[2])  # near enough that both answers occur
    inner, outer = fcl_collide(a, b, -1e-6), fcl_collide(a, b, 1e-6)
    assume(inner == outer)
    assert overlap(a, b) == inner


def test_axis_aligned_boxes_overlap_up_to_touching_and_within_the_margin() -> None:
    eye, h = np.eye(3), np.array([0.1, 0.05, 0.02])
    a = (np.zeros(3), eye, h)
    touching = (np.array([0.2, 0.0, 0.0]), eye, h)
    apart = (np.array([0.2 + 1e-3, 0.0, 0.0]), eye, h)
    assert overlap(a, touching)
    assert not overlap(a, apart)
    assert not overlap(a, apart, margin=0.9e-3)
    assert overlap(a, apart, margin=1.1e-3)


@settings(max_examples=50, deadline=None)
@given(st.lists(boxes, min_size=1, max_size=8), boxes)
def test_a_batch_gives_the_answers_of_its_boxes_one_at_a_time(batch: list[Box], b: Box) -> None:
    batch = [(b[0] + 0.5 * (c - b[0]), r, h) for c, r, h in batch]
    ca, ra, ha = (np.stack(x) for x in zip(*batch, strict=True))
    got = boxes_overlap(ca, ra, ha, *b)
    assert got.shape == (len(batch),)
    assert list(got) == [overlap(x, b) for x in batch]


@pytest.mark.parametrize("shelf", [ShelfSpec(), ShelfSpec(width_m=1.0, depth_m=0.5, height_m=0.4)])
def test_the_interior_box_is_the_interior_corners(shelf: ShelfSpec) -> None:
    box = shelf.interior_box
    assert all(type(v) is float for v in box)
    assert box == (*shelf.interior_lower.tolist(), *shelf.interior_upper.tolist())
    assert box == (-shelf.width_m / 2, 0.0, 0.0, shelf.width_m / 2, shelf.depth_m, shelf.height_m)
