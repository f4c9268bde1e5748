"""DOIG: the collateral disturbance term (paper eq. udiff/doig), exact finalists, the BEV mapped rule."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from msmem_grasp.effect import AnalyticGraspEffect
from msmem_objectives.cdc import CDCConfig, CDCTerm, disturbed_voxels
from msmem_objectives.ig import IGTerm, IGTermConfig
from msmem_push.effect import AnalyticPushEffect
from msmem_push.skill import PushConfig, PushSkill
from msmem_view.skill import ViewAction

from msmem_core.interfaces import CandidateBatch, Prediction
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGService
from msmem_core.msas import Objective, bev_confidence, mapped_fraction
from msmem_core.plugins import get_plugin_manager
from msmem_core.plugins.manager import ComponentRef
from msmem_core.world.voxelize import interior_mask
from tests.test_grasp import BYSTANDER, IN_THE_WAY, TARGET, top_grasp
from tests.test_grasp import box_belief as grasp_box_belief
from tests.test_push import GRID, SHELF, WORKSPACE, _ctx, _small_ig, push_batch, synthetic_belief

C = 15


def _eta(classes: list[int], strength: list[float]) -> np.ndarray:
    """Dirichlet evidence [C, M]: class k with ``strength`` extra evidence on top of the prior 1."""
    eta = np.ones((C, len(classes)), np.float32)
    for m, (k, s) in enumerate(zip(classes, strength, strict=True)):
        eta[k, m] += s
    return eta


def test_u_diff_counts_only_confident_changes_of_known_classes() -> None:
    # voxel 0: known class 3 -> confident class 5 (counted); 1: unknown before -> confident 5 (never);
    # 2: known 3 -> unsure 5 (not confident after); 3: known 3 -> confident 3 (same class);
    # 4: known 3 -> confident 5 but excluded (grasped object's region)
    before = _eta([3, 3, 3, 3, 3], [40, 2, 40, 40, 40])
    after = _eta([5, 5, 5, 3, 5], [40, 40, 3, 40, 40])
    excluded = np.array([False, False, False, False, True])
    assert disturbed_voxels(before, after, 0.5, excluded).tolist() == [True, False, False, False, False]
    assert disturbed_voxels(before, after, 0.5).tolist() == [True, False, False, False, True]
    # chi = C / sum(eta): 15 / (15 + 40) = 0.27 is confident at tau 0.5 but not at tau 0.2
    assert not disturbed_voxels(before, after, 0.2).any()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.05, 1.0))
def test_u_diff_is_monotone_in_exclusion_and_never_exceeds_the_changed_voxels(seed: int, tau: float) -> None:
    rng = np.random.default_rng(seed)
    m = 200
    before = (1.0 + rng.gamma(0.5, 10.0, (C, m))).astype(np.float32)
    after = before.copy()
    moved = rng.random(m) < 0.5
    after[:, moved] = (1.0 + rng.gamma(0.5, 10.0, (C, int(moved.sum())))).astype(np.float32)
    ex = rng.random(m) < 0.3
    full = disturbed_voxels(before, after, tau)
    part = disturbed_voxels(before, after, tau, ex)
    assert not full[~moved].any()  # an unchanged voxel is never disturbed
    assert np.all(part <= full)
    assert not part[ex].any()


def test_cdc_term_on_push_predictions_equals_the_whole_maps() -> None:
    belief = synthetic_belief(5)
    ctx = _ctx(belief)
    actions = PushSkill(PushConfig(max_samples=16)).propose(ctx)
    pred = AnalyticPushEffect().predict(belief, actions, WORKSPACE)
    batch = CandidateBatch("push", "manipulation", list(actions), prediction=pred)
    term = CDCTerm()
    assert term.applies_to == frozenset({"manipulation"})
    sparse = term.score(ctx, batch)
    dense_pred = Prediction.from_beliefs(belief, list(pred.beliefs))  # as a whole-map effect model returns it
    dense = term.score(ctx, CandidateBatch("push", "manipulation", list(actions), prediction=dense_pred))
    np.testing.assert_array_equal(sparse, dense)
    brute = [-float(((belief.vacuity() < 0.5) & (b.vacuity() < 0.5)
                     & (belief.eta.argmax(0) != b.eta.argmax(0))).sum()) for b in pred.beliefs]
    np.testing.assert_array_equal(sparse, brute)
    assert np.all(sparse <= 0)
    assert sparse.min() < 0


def test_cdc_excludes_the_grasped_object_and_sees_the_neighbour_it_displaces() -> None:
    belief = grasp_box_belief([TARGET, IN_THE_WAY, BYSTANDER])
    ctx = _ctx(belief)
    clean = top_grasp(0.0, 0.225, 0.14, 0.04, lift=0.09)  # lifted over the block: only the target leaves
    sweeping = top_grasp(0.0, 0.225, 0.14, 0.04)  # the lifted box drags through the block in front
    pred = AnalyticGraspEffect().predict(belief, [clean, sweeping], WORKSPACE)
    batch = CandidateBatch("grasp", "manipulation", [clean, sweeping], prediction=pred)
    scores = CDCTerm().score(ctx, batch)
    assert scores[0] == 0.0  # intentional removal is not a disturbance
    c = GRID.centers()
    (x0, y0), (x1, y1), h, _ = IN_THE_WAY
    way = (c[..., 0] > x0) & (c[..., 0] < x1) & (c[..., 1] > y0) & (c[..., 1] < y1) & (c[..., 2] > 0) & (c[..., 2] < h)
    assert scores[1] == -float(way.sum())
    # with its own threshold the term is stricter than the run's tau_chi
    assert CDCTerm(CDCConfig(tau_chi=0.01)).score(ctx, batch)[1] == 0.0


def test_cdc_is_a_registered_term_and_the_ours_preset_uses_it() -> None:
    from msmem_core.config import load_config

    pm = get_plugin_manager()
    assert isinstance(pm.build("objective-term", ComponentRef(name="cdc")), CDCTerm)
    ours = load_config(method="ours")
    assert [t.name for t in ours.objective] == ["ig", "semantic-entropy", "cdc"]
    no_cdc = load_config(method="no-cdc")
    assert "cdc" not in [t.name for t in no_cdc.objective]


def test_the_winner_of_a_screened_batch_is_scored_at_full_density() -> None:
    belief, ig, ctx, pred, batch = push_batch(3)
    full = ig.view_ig([ig.prepare(b, before=ctx.field) for b in pred.beliefs]).max(axis=1)
    # a term that favours the candidate the screening ranks last forces a refinement
    screened = IGTerm(IGTermConfig(screen_ray_step=2, finalists=2)).score(ctx, batch)
    last = int(np.argmin(screened))
    assert not np.isclose(screened[last], full[last], rtol=1e-9)

    class Favour(CDCTerm):
        def score(self, ctx: object, batch: CandidateBatch) -> np.ndarray:
            out = np.zeros(len(batch.actions))
            out[last] = 1e9
            return out

    ctx = _ctx(belief, ig=ig)  # fresh cache
    screened_ig = IGTerm(IGTermConfig(screen_ray_step=2, finalists=2))
    objective = Objective([("ig", 1.0, screened_ig), ("favour", 1.0, Favour())])
    i, value, terms, refined = objective.best(ctx, batch)
    assert i == last
    assert refined == 1
    assert terms["ig"] == np.float64(full[last]) or np.isclose(terms["ig"], full[last], rtol=1e-9)
    assert np.isclose(value, full[last] + 1e9, rtol=1e-12)


def test_bev_mapped_fraction_follows_the_belief() -> None:
    interior = interior_mask(SHELF, GRID)
    empty = EvidentialMap.empty(GRID)
    assert mapped_fraction(empty, interior, 0.85) == 0.0  # nothing seen: nothing mapped
    known = grasp_box_belief([TARGET, BYSTANDER])  # every voxel confident (free or a box)
    conf = bev_confidence(known, interior)
    assert conf.shape == GRID.shape[:2]
    assert np.all((conf >= 0) & (conf <= 1))
    assert mapped_fraction(known, interior, 0.85) == 1.0
    half = known.copy()  # forget the left half of the shelf
    left = GRID.centers()[..., 0] < 0.0
    half.alpha[left], half.beta[left], half.eta[:, left] = 1.0, 1.0, 1.0
    assert 0.4 < mapped_fraction(half, interior, 0.85) < 0.6


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["C", "F", "strided"]), st.booleans())
def test_the_counting_kernel_is_the_numpy_rule(seed: int, layout: str, with_excluded: bool) -> None:
    """``count_disturbed`` (one numba pass, what the term uses) counts what ``disturbed_voxels`` marks,
    with thresholds set at voxels' own vacuities (where the order of the float32 class sums decides),
    ties between classes, and the changed evidence in any memory layout."""
    from msmem_objectives.cdc import count_disturbed

    rng = np.random.default_rng(seed)
    n, m = 500, 120
    eta = (1.0 + rng.gamma(0.5, 10.0, (C, n))).astype(np.float32)
    eta[:, :20] = np.float32(7.25)  # every class tied
    idx = rng.choice(n, m, replace=False)
    after = (1.0 + rng.gamma(0.5, 10.0, (C, m))).astype(np.float32)
    after[:, rng.random(m) < 0.3] = eta[:, idx][:, rng.random(m) < 0.3][:, :1]
    if layout == "F":
        after = np.asfortranarray(after)
    elif layout == "strided":
        after = np.repeat(after, 2, axis=1)[:, ::2]
    excluded = rng.random(m) < 0.3 if with_excluded else None
    chi = np.concatenate([C / eta[:, idx].sum(axis=0), C / after.sum(axis=0)])
    for tau in [*rng.choice(chi, 6), 0.5, 1.0]:
        # the threshold as numpy compares it with float32 vacuities: rounded to float32 (1e-12 above is the same)
        for t in (float(tau), float(tau) * (1.0 + 1e-12), float(np.nextafter(np.float32(tau), np.float32(2.0)))):
            want = int(disturbed_voxels(eta[:, idx], after, t, excluded).sum())
            assert count_disturbed(eta, idx, after, t, excluded) == want, (t, layout)


def _every_view(seed: int) -> tuple[EvidentialMap, IGService, CandidateBatch, np.ndarray]:
    """A synthetic belief, the small IG service, a view batch of its every view and their full-density IG."""
    belief = synthetic_belief(seed)
    ig = _small_ig()
    views = np.arange(ig.num_views)
    batch = CandidateBatch("view", "perception", [ViewAction(view=int(v)) for v in views], view_indices=views)
    return belief, ig, batch, ig.view_ig(ig.prepare(belief))


def test_screened_views_keep_the_best_view_and_score_any_winner_at_full_density() -> None:
    belief, ig, batch, full = _every_view(3)
    exact = IGTerm(IGTermConfig(screen_views=False)).score(_ctx(belief, ig=ig), batch)
    screened = IGTerm(IGTermConfig(view_finalists=4)).score(_ctx(belief, ig=ig), batch)
    best = int(np.argmax(exact))
    assert int(np.argmax(screened)) == best
    # the best view keeps its full-density IG and a second view's, found among 4 screened finalists
    assert full[best] < screened[best] <= exact[best]
    others = np.isclose(screened, full, rtol=0, atol=0)
    assert others.sum() == 3  # the other finalists, exact
    rest = ~others
    rest[best] = False
    assert np.all(screened[rest] <= screened[others].min())
    last = int(np.argmin(screened))
    assert screened[last] != full[last]

    class Favour(CDCTerm):  # a term that favours the view the screening ranks last
        applies_to = frozenset({"perception"})

        def score(self, ctx: object, batch: CandidateBatch) -> np.ndarray:
            out = np.zeros(len(batch.actions))
            out[last] = 1e9
            return out

    objective = Objective([("ig", 1.0, IGTerm(IGTermConfig(view_finalists=4))), ("favour", 1.0, Favour())])
    i, value, terms, refined = objective.best(_ctx(belief, ig=ig), batch)
    assert (i, refined) == (last, 1)
    assert terms["ig"] == full[last]
    assert np.isclose(value, full[last] + 1e9, rtol=1e-12)


def test_the_second_view_is_added_only_where_manipulation_is_allowed() -> None:
    belief, ig, batch, full = _every_view(3)
    best = int(np.argmax(full))
    exact = IGTermConfig(screen_views=False)
    allowed = IGTerm(exact).score(_ctx(belief, ig=ig), batch)
    alone = IGTerm(exact).score(_ctx(belief, allowed=False, ig=ig), batch)
    always = IGTerm(exact.model_copy(update={"two_step_always": True})).score(_ctx(belief, allowed=False, ig=ig), batch)
    np.testing.assert_array_equal(alone, full)  # views compete only among themselves: no lookahead
    assert allowed[best] > full[best]
    np.testing.assert_array_equal(always, allowed)
    assert int(np.argmax(alone)) == int(np.argmax(allowed)) == best  # the same view wins either way
    off = IGTerm(exact.model_copy(update={"two_step": False, "two_step_always": True}))
    np.testing.assert_array_equal(off.score(_ctx(belief, ig=ig), batch), full)
