"""IG credits only information a camera can gain: a manipulation's predicted change moves occupancy (what
the view after it sees past) but adds no entropy of its own (``IGConfig.predicted_entropy``)."""

from __future__ import annotations

import numpy as np
from msmem_grasp.effect import AnalyticGraspEffect, GraspEffectConfig
from msmem_objectives.ig import IGTerm

from msmem_core.interfaces import CandidateBatch
from msmem_core.map.ig import IGConfig, IGService
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints
from tests.test_grasp import BYSTANDER, IN_THE_WAY, TARGET, WORKSPACE, box_belief, ctx, top_grasp
from tests.test_push import GRID, SHELF, SMALL_CAM

MEM = {"gain": "entropy", "information": "occupancy"}
"""MEM's IG (the paper): a voxel counts the entropy of its clamped occupancy."""


def _service(rule: str, mem: bool = True) -> IGService:
    views = generate_viewpoints(ViewpointConfig(), SHELF)[::15]
    extra = MEM if mem else {}
    return IGService(GRID, SMALL_CAM, views, SHELF, IGConfig(predicted_entropy=rule, **extra))  # type: ignore[arg-type]


def _known_shelf_with_an_open_unknown_patch():
    """Every voxel confidently known (three boxes, free space around), except a small never-observed
    patch in the open, in plain view of the cameras: the views have something to gain, and grasping
    the front box opens nothing that was not already known."""
    b = box_belief([TARGET, IN_THE_WAY, BYSTANDER])
    c = GRID.centers()
    patch = (np.abs(c[..., 0] + 0.25) < 0.02) & (np.abs(c[..., 1] - 0.05) < 0.02)
    patch &= (c[..., 2] > 0.0) & (c[..., 2] < 0.04)
    b.alpha[patch], b.beta[patch], b.eta[:, patch] = 1.0, 1.0, 1.0
    return b


def _view_and_grasp(rule: str, mem: bool = True, target: str = "prior") -> tuple[float, float]:
    """The best view's and the front box's grasp's IG term; ``mem``: MEM's voxel entropy (else the
    library default, the expected reduction of occupancy and class entropy); ``target``: what the
    analytic grasp model makes of the grasped box (``prior``: MEM's rule; ``free``: the default)."""
    belief = _known_shelf_with_an_open_unknown_patch()
    ig = _service(rule, mem)
    c = ctx(belief, ig=ig)
    (x0, y0), (x1, y1), h, cls = IN_THE_WAY
    grasp = top_grasp((x0 + x1) / 2, (y0 + y1) / 2, h - 0.02, y1 - y0, cls=cls)
    pred = AnalyticGraspEffect(GraspEffectConfig(target=target)).predict(belief, [grasp], WORKSPACE)  # type: ignore[arg-type]
    assert len(pred.changes[0].idx) > 100  # the grasped box's voxels change
    views = np.arange(ig.num_views)
    term = IGTerm()
    view_value = float(term.score(c, CandidateBatch("view", "perception", [], view_indices=views)).max())
    grasp_value = float(term.score(c, CandidateBatch("grasp", "manipulation", [grasp], prediction=pred))[0])
    return view_value, grasp_value


def test_a_manipulation_that_opens_no_never_observed_voxel_does_not_beat_the_best_view() -> None:
    view_value, grasp_value = _view_and_grasp("no-gain")
    assert view_value > 1.0  # the patch is worth looking at
    assert grasp_value <= view_value


def test_under_the_library_defaults_too_a_grasp_that_opens_nothing_does_not_beat_the_best_view() -> None:
    view_value, grasp_value = _view_and_grasp("no-gain", mem=False, target="free")
    assert view_value > 0.3  # the patch is worth looking at
    assert grasp_value <= view_value


def test_the_entropy_a_prediction_injects_is_what_made_such_a_grasp_win() -> None:
    view_value, grasp_value = _view_and_grasp("as-predicted")  # MEM's rule: the prior's entropy counts
    assert grasp_value > view_value
