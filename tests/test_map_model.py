"""The whole-map observation model (``cnabu-map``) and its column-fill twin.

``tests/data/map_heldout/`` holds two shards of ``msmem datagen cnabu --kind observe --seed 900000
--scenes 2 --samples 12 --min-views 0 --max-views 0`` (held-out seeds: the shipped weights were
trained on seeds 100000 and up, below 900000; see ``plugins/msmem_cnabu/weights/MODEL_CARD_map.md``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from msmem_analytic.columnfill import ColumnFillObservationModel
from msmem_analytic.observation import AnalyticObservationModel
from msmem_cnabu.learn.datagen import load_shard
from msmem_cnabu.learn.mapeval import evaluate_rollouts
from msmem_cnabu.learn.maptrain import MapTrainConfig, rollout_loss, train_map
from msmem_cnabu.learn.rollouts import sequence, start_masks
from msmem_cnabu.mapnet import MapNet, MapNetConfig, analytic_update, bounded_evidence
from msmem_cnabu.weights import load_map_net

from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.world.grid import GridSpec

HELDOUT = Path(__file__).parent / "data" / "map_heldout"
SHIPPED = Path(__file__).parents[1] / "plugins" / "msmem_cnabu" / "weights" / "cnabu_map.pt"


@pytest.fixture(scope="module")
def shard():
    return load_shard(sorted(HELDOUT.glob("scene_*.npz"))[0])


# ------------------------------------------------------------------------------ bounded evidence
@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-40, 40), min_size=16, max_size=16), st.floats(-40, 40),
       st.sampled_from([(100.0, 300.0), (10.0, 20.0)]))
def test_bounded_evidence_is_at_least_one_bounded_and_has_the_predicted_means(cls, occ, bounds):
    s_max, t_max = bounds
    o = torch.tensor([occ], dtype=torch.float64)
    c = torch.tensor([cls[:15]], dtype=torch.float64)
    a, b, e, p, q = bounded_evidence(o, c, s_max, t_max)
    assert float(a.min()) >= 1 - 1e-9
    assert float(b.min()) >= 1 - 1e-9
    assert float(e.min()) >= 1 - 1e-9
    assert float((a + b).max()) <= s_max + 1e-6
    assert float(e.sum(1).max()) <= t_max + 1e-6
    assert 0 <= float(p.min())
    assert float(p.max()) <= 1
    assert torch.allclose(a / (a + b), p)
    assert torch.allclose(e / e.sum(1, keepdim=True), q)


def test_an_even_prediction_is_the_prior():
    a, b, e, _, _ = bounded_evidence(torch.zeros(1, 3), torch.zeros(1, 15, 3), 100.0, 300.0)
    assert torch.allclose(a, torch.ones(1, 3))
    assert torch.allclose(b, torch.ones(1, 3))
    assert torch.allclose(e, torch.ones(1, 15, 3))


# ------------------------------------------------------------------------------ analytic step
def test_the_networks_analytic_step_is_the_analytic_observation_update(shard):
    f0, o0, s0 = start_masks(shard)
    model = AnalyticObservationModel()
    b0 = model.apply_masks(EvidentialMap.empty(shard.grid), f0, o0, s0)
    assert np.array_equal(b0.alpha, shard.alpha[0].astype(np.float32))  # the start view recovered exactly
    assert np.array_equal(b0.eta, shard.eta[0].astype(np.float32))
    f, o, s = shard.masks(0)
    want = model.apply_masks(b0, f, o, s)
    t = torch.from_numpy
    a, b, e = analytic_update(t(b0.alpha)[None], t(b0.beta)[None], t(b0.eta)[None], t(f)[None], t(o)[None],
                              t(s)[None], 10.0)
    assert np.array_equal(a[0].numpy(), want.alpha)
    assert np.array_equal(b[0].numpy(), want.beta)
    assert np.array_equal(e[0].numpy(), want.eta)


def test_an_untrained_network_is_the_bounded_analytic_update(shard):
    seq = sequence(shard)
    net = MapNet(MapNetConfig(grid_shape=seq.gt_occ.shape)).eval()
    b = AnalyticObservationModel().apply_masks(EvidentialMap.empty(shard.grid), seq.free[0], seq.occ[0], seq.seen[0])
    t = torch.from_numpy
    with torch.no_grad():
        a, bb, e = net.step(t(b.alpha)[None], t(b.beta)[None], t(b.eta)[None], t(seq.free[1])[None],
                            t(seq.occ[1])[None], t(seq.seen[1])[None], t(seq.valid))
    ref = AnalyticObservationModel().apply_masks(b, seq.free[1], seq.occ[1], seq.seen[1])
    eps = 2 / net.config.s_max  # the floor mixed into every probability
    p_ref = eps / 2 + (1 - eps) * ref.expected_occupancy()
    p = (a / (a + bb))[0].numpy()
    assert np.allclose(p, p_ref, atol=2e-3)
    assert np.array_equal(np.argmax(e[0].numpy(), 0), np.argmax(ref.eta, 0))


# ------------------------------------------------------------------------------ shipped weights
def test_shipped_weights_load_as_plain_tensors_and_stay_small():
    net, meta = load_map_net(SHIPPED)
    assert not net.training
    assert SHIPPED.stat().st_size < 8e6
    assert meta["data"]["seed_max"] < 900000  # the held-out shards are seeds 900000 and up


@pytest.fixture(scope="module")
def heldout(tmp_path_factory):
    """``msmem eval map`` on the held-out shards, as a user runs it: its JSON's final scores."""
    from typer.testing import CliRunner

    from msmem_core.cli.app import build_app

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("eval") / "map.json"
    res = CliRunner().invoke(build_app(), ["eval", "map", "--data", str(HELDOUT), "--threads", "1", "--json", str(out)])
    assert res.exit_code == 0, res.output
    return json.loads(out.read_text())["final"]


def test_shipped_weights_beat_the_analytic_update_on_heldout_scenes(heldout):
    learned, analytic = heldout["cnabu-map"], heldout["analytic-observation"]
    assert learned["occ_nll"] + learned["sem_nll"] < analytic["occ_nll"] + analytic["sem_nll"], (learned, analytic)
    assert learned["occupancy_miou"] > analytic["occupancy_miou"]


def test_eval_map_scores_the_default_belief_which_keeps_what_rays_labelled(heldout):
    """The belief an episode uses (the network with the ray record's authority) keeps the classes rays
    gave: its 2-D semantics are at least the analytic update's, where the raw network's are not, and it
    keeps the network's occupancy."""
    default, learned, analytic = (heldout[k] for k in ("cnabu-map (default belief)", "cnabu-map",
                                                        "analytic-observation"))
    assert default["semantic_miou_2d"] >= analytic["semantic_miou_2d"], (default, analytic)
    assert default["semantic_miou_2d"] > learned["semantic_miou_2d"]
    assert default["occupancy_miou"] > analytic["occupancy_miou"] + 0.2


def test_a_long_rollout_keeps_evidence_at_least_one_and_bounded(shard):
    net, _ = load_map_net(SHIPPED)
    seq = sequence(shard)
    cfg = net.config
    rng = np.random.default_rng(0)
    b = EvidentialMap.empty(shard.grid)
    t = torch.from_numpy
    for k in range(40):  # the recorded views, then again in a random order, as an episode revisits places
        i = k if k < len(seq) else int(rng.integers(len(seq)))
        with torch.no_grad():
            a, bb, e = net.step(t(b.alpha)[None], t(b.beta)[None], t(b.eta)[None], t(seq.free[i])[None],
                                t(seq.occ[i])[None], t(seq.seen[i])[None], t(seq.valid))
        b = EvidentialMap(shard.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())
        assert b.alpha.min() >= 1 - 1e-4
        assert b.beta.min() >= 1 - 1e-4
        assert b.eta.min() >= 1 - 1e-4
        assert (b.alpha + b.beta).max() <= cfg.s_max * (1 + 1e-5)
        assert b.eta.sum(0).max() <= cfg.t_max * (1 + 1e-5)
        p = b.expected_occupancy()
        assert np.isfinite(p).all()
        assert p.min() >= 0
        assert p.max() <= 1


# ------------------------------------------------------------------------------ training
@pytest.mark.slow  # training; the fast suite keeps test_train_map_writes_loadable_weights_with_a_sidecar (one batch)
def test_rollout_training_lowers_the_loss_on_its_scene(shard, tmp_path):
    """Real training on one recorded scene: its rollout loss falls."""
    torch.manual_seed(0)
    seq = sequence(shard)
    net = MapNet(MapNetConfig(grid_shape=seq.gt_occ.shape, width=16, embed=4, context=4, hidden=16))
    from msmem_cnabu.learn.maptrain import _batch

    batch = _batch([seq], [False])
    valid = torch.from_numpy(seq.valid)
    before = rollout_loss(net.eval(), batch, valid)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3)
    for _ in range(3):
        rollout_loss(net.train(), batch, valid, 1.0, opt)
    after = rollout_loss(net.eval(), batch, valid)
    assert sum(x[0] + x[1] for x in after) < sum(x[0] + x[1] for x in before)


def test_train_map_writes_loadable_weights_with_a_sidecar(tmp_path):
    side = train_map(HELDOUT, tmp_path / "m.pt", MapTrainConfig(batches=1, batch=1),
                     MapNetConfig(width=8, embed=2, context=2, hidden=8, levels=2), log=lambda _: None)
    assert side["data"]["scenes"] == 1
    assert side["stopped"] == "epochs"
    net, meta = load_map_net(tmp_path / "m.pt")
    assert meta["sha256"] == side["sha256"]
    assert net.config.width == 8


# ------------------------------------------------------------------------------ column-fill
def _grid() -> GridSpec:
    return GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.01, shape=(4, 4, 8))


def test_column_fill_marks_unseen_voxels_under_a_seen_top_and_removes_them_when_it_goes():
    grid = _grid()
    model = ColumnFillObservationModel()
    b = EvidentialMap.empty(grid)
    free = np.zeros(grid.shape, bool)
    occ = np.zeros(grid.shape, bool)
    seen = np.zeros((b.num_classes, *grid.shape), bool)
    occ[1, 1, 5] = True  # a top surface seen at z = 5 with class 3
    seen[3, 1, 1, 5] = True
    free[1, 1, 6:7] = True  # the ray above it
    free[2, 1, 1:7] = True  # a free column
    out = model.update_masks(b, free, occ, seen)
    filled = model.filled(out)
    want = np.zeros(grid.shape, bool)
    want[1, 1, 1:5] = True  # the margin (z = 0) is the board: never filled
    assert np.array_equal(filled, want)
    assert (out.expected_occupancy()[1, 1, 1:5] > 0.5).all()
    assert (np.argmax(out.eta[:, 1, 1, 1:5], 0) == 3).all()
    assert not filled[2].any()  # nothing is believed occupied in the free column
    # a second view sees the top voxel free: the fill under it goes with it
    free2 = np.zeros(grid.shape, bool)
    free2[1, 1, 5] = True
    out2 = model.update_masks(out, free2, np.zeros(grid.shape, bool), np.zeros_like(seen))
    assert not model.filled(out2).any()
    assert (out2.alpha[1, 1, 1:5] == 1).all()
    assert (out2.eta[:, 1, 1, 1:5] == 1).all()


def test_column_fill_never_changes_observed_voxels(shard):
    seq = sequence(shard)
    analytic, fill = AnalyticObservationModel(), ColumnFillObservationModel()
    a = f = EvidentialMap.empty(shard.grid)
    for t in range(len(seq)):
        a = analytic.apply_masks(a, seq.free[t], seq.occ[t], seq.seen[t])
        f = fill.update_masks(f, seq.free[t], seq.occ[t], seq.seen[t])
    observed = (a.alpha > 1) | (a.beta > 1)
    assert np.array_equal(a.alpha[observed], f.alpha[observed])
    assert np.array_equal(a.beta[observed], f.beta[observed])
    assert np.array_equal(a.eta[:, observed], f.eta[:, observed])
    assert fill.filled(f).sum() > 100  # something was filled in a real scene


# ------------------------------------------------------------------------------ v2 options
def test_nearest_known_class_is_the_class_of_a_nearest_known_voxel():
    """Against brute force: the distance is the least distance to a known voxel, and the class
    distribution is that of a known voxel at that distance."""
    from msmem_cnabu.mapnet import nearest_known_class

    rng = np.random.default_rng(3)
    shape = (7, 5, 6)
    logit = torch.from_numpy(rng.normal(size=(2, *shape)).astype(np.float32))
    obj = torch.softmax(torch.from_numpy(rng.normal(size=(2, 4, *shape)).astype(np.float32) * 3), 1)
    valid = torch.from_numpy(rng.random(shape) > 0.2)
    out = nearest_known_class(logit, obj, valid, scale=100.0)
    known = (logit > 0) & (obj.amax(1) > 0.5) & valid
    idx = np.argwhere(np.ones(shape, bool))
    for i in range(2):
        ks = np.argwhere(known[i].numpy())
        assert len(ks)
        d = np.sqrt(((idx[:, None, :] - ks[None]) ** 2).sum(-1))  # [voxels, known]
        dmin = d.min(1)
        np.testing.assert_allclose(out[i, -1].numpy().ravel(), dmin / 100.0, atol=1e-5)
        got = out[i, :-1].numpy().reshape(4, -1).T
        for v in range(len(idx)):
            near = ks[np.isclose(d[v], dmin[v])]
            cands = obj[i][:, near[:, 0], near[:, 1], near[:, 2]].numpy().T
            assert np.isclose(cands, got[v], atol=1e-6).all(1).any()


def test_nearest_known_class_without_known_voxels_is_uniform_and_far():
    from msmem_cnabu.mapnet import nearest_known_class

    out = nearest_known_class(-torch.ones(1, 3, 3, 3), torch.full((1, 4, 3, 3, 3), 0.25),
                              torch.ones(3, 3, 3, dtype=bool), 10.0)
    assert torch.allclose(out[0, :-1], torch.full((4, 3, 3, 3), 0.25))
    assert torch.allclose(out[0, -1], torch.ones(3, 3, 3))


def _small(**kw):
    return MapNetConfig(grid_shape=(16, 8, 6), width=8, embed=2, context=2, hidden=8, levels=2, **kw)


def _random_inputs(cfg, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape, c = cfg.grid_shape, cfg.num_classes
    a = 1 + 5 * torch.rand(1, *shape, generator=g)
    b = 1 + 5 * torch.rand(1, *shape, generator=g)
    e = 1 + 5 * torch.rand(1, c, *shape, generator=g)
    free = torch.rand(1, *shape, generator=g) > 0.7
    occ = ~free & (torch.rand(1, *shape, generator=g) > 0.8)
    seen = torch.zeros(1, c, *shape, dtype=bool)
    seen[:, 3] = occ
    return a, b, e, free, occ, seen, torch.ones(shape, dtype=bool)


def test_the_object_class_head_ties_the_free_class_to_the_occupancy():
    torch.manual_seed(0)
    net = MapNet(_small(class_head="object")).eval()
    torch.nn.init.normal_(net.head[-1].weight, std=0.5)
    o, c = net(*_random_inputs(net.config))
    q = torch.softmax(c, 1)
    assert torch.allclose(q[:, 0], torch.sigmoid(-o), atol=1e-5)
    assert torch.allclose(q.sum(1), torch.ones_like(o), atol=1e-5)


def test_the_object_head_class_loss_ignores_free_voxels():
    from msmem_cnabu.learn.maploss import map_loss

    occ = torch.zeros(1, 4, 1, 1, dtype=bool)
    occ[0, :2] = True
    cls = torch.where(occ, 2, 0).long()
    o = torch.zeros(1, 4, 1, 1)
    c1 = torch.zeros(1, 5, 4, 1, 1)
    c2 = c1.clone()
    c2[0, 0, 2:] = 9.0  # only free voxels' class logits change
    valid = torch.ones(4, 1, 1, dtype=bool)
    l1 = map_loss(o, c1, occ, cls, valid, 100.0, 300.0, occupied_only=True)[1]
    l2 = map_loss(o, c2, occ, cls, valid, 100.0, 300.0, occupied_only=True)[1]
    assert torch.isclose(l1, l2)
    assert not torch.isclose(map_loss(o, c1, occ, cls, valid, 100.0, 300.0)[1],
                             map_loss(o, c2, occ, cls, valid, 100.0, 300.0)[1])


def _top_view_nll_by_enumeration(p, q, gt_cls, valid):
    """Mean over columns with an interior voxel of -log P(top-view class = ground truth's), summing
    over every occupancy configuration of the column (voxels independent; outside voxels free)."""
    import itertools

    from msmem_core.run.metrics import top_view_classes

    gt_top = top_view_classes(np.where(valid, gt_cls, 0))
    nll = []
    for x, y in zip(*np.nonzero(valid.any(-1)), strict=True):
        pz = np.where(valid[x, y], p[x, y], 0.0)
        prob = 0.0
        for occ in itertools.product((0, 1), repeat=pz.size):
            w = float(np.prod(np.where(occ, pz, 1.0 - pz)))
            if not any(occ):
                prob += w * (gt_top[x, y] == 0)
            elif gt_top[x, y] > 0:
                zt = max(z for z, o in enumerate(occ) if o)
                r = q[1:, x, y, zt] / q[1:, x, y, zt].sum()
                prob += w * r[gt_top[x, y] - 1]
        nll.append(-math.log(prob))
    return float(np.mean(nll))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["joint", "object"]))
def test_top_view_loss_is_the_nll_of_the_top_view_class_map(seed, head):
    """``top_view_loss`` equals the brute-force probability, over every occupancy configuration of
    each column, that its highest occupied interior voxel has the ground truth's top class."""
    from msmem_cnabu.learn.maploss import top_view_loss

    g = torch.Generator().manual_seed(seed)
    o = torch.randn(1, 3, 2, 4, generator=g) * 3
    c = torch.randn(1, 5, 3, 2, 4, generator=g) * 2
    if head == "object":  # q = [1 - p, p r]
        c = torch.cat([torch.nn.functional.logsigmoid(-o)[:, None],
                       torch.nn.functional.logsigmoid(o)[:, None] + torch.log_softmax(c[:, 1:], 1)], 1)
    valid = torch.rand(3, 2, 4, generator=g) > 0.2
    gt = torch.randint(0, 5, (1, 3, 2, 4), generator=g)
    _, _, _, p, q = bounded_evidence(o, c, 100.0, 300.0)
    want = _top_view_nll_by_enumeration(p[0].double().numpy(), q[0].double().numpy(), gt[0].numpy(), valid.numpy())
    got = float(top_view_loss(o, c, gt, valid, 100.0, 300.0))
    assert got == pytest.approx(want, rel=1e-4, abs=1e-5)


def test_top_view_loss_charges_an_occupied_voxel_above_the_object():
    """A confident false voxel of another class above the true top takes the column's top view: the
    loss rises, though the per-voxel NLL of the true surface is unchanged."""
    from msmem_cnabu.learn.maploss import top_view_loss

    valid = torch.ones(1, 1, 4, dtype=bool)
    gt = torch.tensor([[[[2, 2, 0, 0]]]])
    o = torch.tensor([[[[9.0, 9.0, -9.0, -9.0]]]])
    c = torch.full((1, 4, 1, 1, 4), -9.0)
    c[:, 2] = 9.0
    clean = float(top_view_loss(o, c, gt, valid, 100.0, 300.0))
    o2, c2 = o.clone(), c.clone()
    o2[..., 3] = 9.0
    c2[:, 2, ..., 3], c2[:, 3, ..., 3] = -9.0, 9.0
    assert clean < 0.1
    assert float(top_view_loss(o2, c2, gt, valid, 100.0, 300.0)) > 1.0


def test_a_widened_network_starts_as_the_old_one():
    """--init from weights without the nearest-class features: the new inputs get zero weights, so
    the widened network computes what the old one did."""
    from msmem_cnabu.learn.maptrain import load_widened

    torch.manual_seed(1)
    old = MapNet(_small()).eval()
    torch.nn.init.normal_(old.head[-1].weight, std=0.5)
    new = MapNet(_small(nearest_class=True)).eval()
    load_widened(new, old.state_dict(), "old.pt")
    x = _random_inputs(old.config, seed=2)
    for u, v in zip(old(*x), new(*x), strict=True):
        assert torch.allclose(u, v, atol=1e-5)


def test_bad_network_settings_name_the_field(tmp_path):
    from msmem_core.errors import UserError

    with pytest.raises(UserError, match="field class_head"):
        train_map(HELDOUT, tmp_path / "m.pt", MapTrainConfig(batches=1, batch=1), arch={"class_head": "rainbow"},
                  log=lambda _: None)


# ------------------------------------------------------------------------------ post-manipulation sequences
POSTMANIP = dict(kind="observe", min_views=0, max_views=0, observe_samples=4, manipulate_after=2)
ANALYTIC_EFFECTS = {"push": {"name": "push-analytic", "params": {}}, "grasp": {"name": "grasp-analytic", "params": {}}}
"""The effect models a rollout applies unless others are named (``rollouts.default_effect_models``)."""
"""``msmem datagen cnabu --kind observe --samples 4 --min-views 0 --max-views 0 --manipulate-after 2``
(about 8 s per scene on a loaded machine)."""


@pytest.fixture(scope="module")
def postmanip_dir(tmp_path_factory):
    from msmem_cnabu.learn.datagen import CNABUDataConfig, generate_dataset

    out = tmp_path_factory.mktemp("postmanip")
    summary = generate_dataset(out, [900000], CNABUDataConfig(**POSTMANIP), progress=False, log=lambda _: None)
    summary.raise_if_failed()
    return out


@pytest.fixture(scope="module")
def postmanip(postmanip_dir):
    return load_shard(postmanip_dir / "scene_900000.npz")


def test_a_post_manipulation_shard_records_a_real_push_that_moved_objects(postmanip):
    info = postmanip.info["manipulation"]
    assert info["executed"]
    assert info["skill"] == "push"
    assert info["candidates"] > 0
    k = info["sample"]
    assert k == 2  # after the two views recorded before it
    kinds = [postmanip.manipulation(i) is not None for i in range(len(postmanip))]
    assert kinds == [False, False, True, False, False]  # 4 views, the push after the second
    assert type(postmanip.manipulation(k)).__name__ == "PushAction"
    assert not postmanip.act_vox[k].any()  # a manipulation has no ray masks
    assert info["displacement_m"]
    assert max(info["displacement_m"].values()) > 0.02
    before, after = postmanip.gt_occ[k - 1], postmanip.gt_occ[k]
    assert (before != after).sum() == info["voxels_changed"] > 100  # the world really changed
    assert np.array_equal(postmanip.gt_occ_before[postmanip.state[k]], before)
    for i in range(k, len(postmanip)):  # every later view sees the moved world
        assert np.array_equal(postmanip.gt_occ[i], after)


def test_post_manipulation_shards_are_deterministic_and_resumable(postmanip_dir, postmanip):
    from msmem_cnabu.learn.datagen import CNABUDataConfig, generate_dataset, make_shard

    again = make_shard(900000, CNABUDataConfig(**POSTMANIP)).arrays()
    for key, value in postmanip.arrays().items():
        if key != "info":
            assert np.array_equal(np.asarray(again[key]), np.asarray(value)), key
    info = json.loads(str(again["info"]))
    assert info.pop("sim_execute_s") > 0  # the one field that is a measurement, not data
    assert info == {k: v for k, v in postmanip.info.items() if k != "sim_execute_s"}
    summary = generate_dataset(postmanip_dir, [900000], CNABUDataConfig(**POSTMANIP), progress=False,
                               log=lambda _: None)
    assert not summary.generated  # the finished shard is kept


def test_manipulate_after_must_leave_views_to_follow():
    from msmem_cnabu.learn.datagen import CNABUDataConfig
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="views must follow"):
        CNABUDataConfig(**{**POSTMANIP, "manipulate_after": 4})


GRASPMANIP = dict(kind="observe", min_views=0, max_views=0, observe_samples=6, manipulate_after=3,
                  manipulate_skill="grasp", manipulate_tries=2)
"""``msmem datagen cnabu --kind observe --samples 6 --min-views 0 --max-views 0 --manipulate-after 3
--manipulate-skill grasp --manipulate-tries 2``: on scene 600003 the grasp skill proposes nothing after
3 views and 2 grasps after the fourth."""


@pytest.fixture(scope="module")
def graspmanip():
    from msmem_cnabu.learn.datagen import CNABUDataConfig, make_shard

    return make_shard(600003, CNABUDataConfig(**GRASPMANIP))


@pytest.mark.slow  # two scenes simulated (about 20 s)
def test_a_grasp_sequence_removes_the_held_object_and_later_views_see_it_gone(graspmanip):
    from msmem_cnabu.learn.datagen import CNABUDataConfig, make_shard
    from msmem_cnabu.learn.rollouts import Effects
    from msmem_grasp.skill import GraspAction

    s = graspmanip
    info = s.info["manipulation"]
    assert info["skill"] == "grasp"
    assert info["effect_model"] == "grasp-analytic"
    assert info["executed"]
    assert info["success"]
    assert len(info["removed"]) == 1
    k = info["sample"]
    assert k == 4  # asked after views 3 (nothing) and 4 (the second try)
    assert [s.manipulation(i) is not None for i in range(len(s))] == [False] * 4 + [True] + [False] * 2
    action = s.manipulation(k)
    assert isinstance(action, GraspAction)
    before, after = s.gt_occ[k - 1], s.gt_occ[k]
    assert after.sum() < before.sum() - 500  # the object left the shelf
    assert (before & ~after).sum() == info["voxels_changed"]  # and nothing appeared
    for i in range(k, len(s)):
        assert np.array_equal(s.gt_occ[i], after)
    seq = sequence(s)
    assert list(seq.manipulations) == [5]  # after the start view and four recorded views
    grasped = Effects().apply(EvidentialMap(s.grid, s.alpha[s.state[k]].astype(np.float32),
                                            s.beta[s.state[k]].astype(np.float32),
                                            s.eta[s.state[k]].astype(np.float32)), action, s.workspace)
    p0 = s.alpha[s.state[k]].astype(np.float64) / (s.alpha[s.state[k]] + s.beta[s.state[k]])
    assert (grasped.expected_occupancy() < p0 - 0.1).sum() > 100  # grasp-analytic takes the object out
    # one try only: the skill proposed nothing after 3 views, and the sequence is a plain one
    once = make_shard(600003, CNABUDataConfig(**{**GRASPMANIP, "manipulate_tries": 1}))
    assert once.info["manipulation"]["executed"] is False
    assert all(once.manipulation(i) is None for i in range(len(once)))
    assert np.array_equal(once.act_vox[:4], s.act_vox[:4])  # the same views up to the grasp


def test_the_sequence_exposes_the_push_and_the_ground_truth_of_every_view(postmanip):
    seq = sequence(postmanip)
    assert len(seq) == 5  # the start view and the 4 recorded views
    assert list(seq.manipulations) == [3]  # after the start view and two recorded views
    assert seq.manipulations[3] == postmanip.manipulation(2)
    assert not seq.mirror_ok  # the push is not mirrored
    k = 2
    for t in range(3):
        assert np.array_equal(seq.step_gt_occ[t], postmanip.gt_occ[k - 1])  # before the push
    for t in (3, 4):
        assert np.array_equal(seq.step_gt_occ[t], postmanip.gt_occ[k])  # after it
        assert np.array_equal(seq.step_gt_cls[t], postmanip.gt_cls[k])
    assert np.array_equal(seq.gt_occ, postmanip.gt_occ[-1])
    assert np.array_equal(seq.free[3], postmanip.masks(3)[0])  # the first view after the push


def test_a_rollout_applies_the_push_and_scores_later_views_against_the_moved_world(postmanip):
    """The loss after each view is against the ground truth after that view: after the push the
    post-push truth (with the pre-push truth the losses would differ), and at the push the network's
    belief becomes the push-analytic prediction of its own output, bounded, without gradient."""
    from msmem_cnabu.learn.datagen import predicted_belief
    from msmem_cnabu.learn.maploss import map_loss
    from msmem_cnabu.learn.maptrain import _batch
    from msmem_cnabu.learn.rollouts import Effects, bounded_map
    from msmem_push.effect import AnalyticPushEffect

    torch.manual_seed(0)
    seq = sequence(postmanip)
    net = MapNet(MapNetConfig(grid_shape=seq.step_gt_occ.shape[1:], width=8, embed=2, context=2, hidden=8,
                              levels=2)).eval()
    torch.nn.init.normal_(net.head[-1].weight, std=0.05)  # not the plain analytic update
    batch = _batch([seq], [False])
    valid = torch.from_numpy(seq.valid)
    trace: list = []
    effects = Effects()
    assert effects.record() == ANALYTIC_EFFECTS
    losses = rollout_loss(net, batch, valid, effects=effects, trace=trace)
    assert len(losses) == len(trace) == 5
    cfg = net.config
    pre = postmanip.gt_occ[1], postmanip.gt_cls[1]
    post = postmanip.gt_occ[2], postmanip.gt_cls[2]

    def loss(t, gt):
        o, c = trace[t]
        lo, lc = map_loss(o, c, torch.from_numpy(gt[0])[None], torch.from_numpy(gt[1].astype(np.int64))[None], valid,
                          cfg.s_max, cfg.t_max)
        return lo.item(), lc.item()

    for t in range(5):
        want = loss(t, pre if t < 3 else post)
        assert np.allclose(losses[t][:2], want, rtol=1e-5), t
    for t in (3, 4):
        assert not np.allclose(losses[t][0], loss(t, pre)[0], rtol=1e-3)  # the planted bug would show
    # the input of view 3 is the bounded push-analytic prediction of the output after view 2
    from msmem_cnabu.mapnet import bounded_evidence

    a, b, e, _, _ = bounded_evidence(*trace[2], cfg.s_max, cfg.t_max)
    before = EvidentialMap(postmanip.grid, a[0].numpy(), b[0].numpy(), e[0].numpy())
    pushed = bounded_map(predicted_belief(AnalyticPushEffect(), before, seq.manipulations[3], seq.workspace),
                         cfg.s_max, cfg.t_max)
    assert (pushed.expected_occupancy() != before.expected_occupancy()).sum() > 100  # the push moved evidence
    t_ = torch.from_numpy
    with torch.no_grad():
        o3, _ = net(t_(pushed.alpha)[None], t_(pushed.beta)[None], t_(pushed.eta)[None], t_(seq.free[3])[None],
                    t_(seq.occ[3])[None], t_(seq.seen[3])[None], valid)
    assert torch.allclose(o3, trace[3][0], atol=1e-4)
    for x in (pushed.alpha, pushed.beta):
        assert x.min() >= 1 - 1e-4
    assert (pushed.alpha + pushed.beta).max() <= cfg.s_max * (1 + 1e-5)
    assert pushed.eta.sum(0).max() <= cfg.t_max * (1 + 1e-5)


def test_bounded_map_keeps_the_networks_form_and_bounds_anything_else():
    from msmem_cnabu.learn.rollouts import bounded_map

    grid = _grid()
    a, b, e, _, _ = bounded_evidence(torch.randn(1, *grid.shape) * 5, torch.randn(1, 15, *grid.shape) * 5, 100.0, 300.0)
    own = EvidentialMap(grid, a[0].numpy(), b[0].numpy(), e[0].numpy())
    again = bounded_map(own, 100.0, 300.0)
    for x, y in ((own.alpha, again.alpha), (own.beta, again.beta), (own.eta, again.eta)):
        np.testing.assert_allclose(x, y, rtol=1e-4)
    rng = np.random.default_rng(0)
    wild = EvidentialMap(grid, rng.uniform(1, 1e4, grid.shape).astype(np.float32),
                         rng.uniform(1, 3, grid.shape).astype(np.float32),
                         rng.uniform(1, 1e4, (15, *grid.shape)).astype(np.float32))
    out = bounded_map(wild, 100.0, 300.0)
    assert out.alpha.min() >= 1 - 1e-4
    assert out.beta.min() >= 1 - 1e-4
    assert out.eta.min() >= 1 - 1e-4
    assert (out.alpha + out.beta).max() <= 100 * (1 + 1e-5)
    assert out.eta.sum(0).max() <= 300 * (1 + 1e-5)
    assert np.array_equal(np.argmax(out.eta, 0), np.argmax(wild.eta, 0))


def test_the_twins_go_through_the_same_push_with_the_same_effect_model(postmanip_dir, postmanip):
    """Every model's belief before the view after the push is the push-analytic prediction of its belief
    after the view before it; the learned model and both twins are scored."""
    from msmem_cnabu.learn.datagen import predicted_belief
    from msmem_cnabu.learn.mapeval import twins
    from msmem_push.effect import AnalyticPushEffect

    calls: dict[str, list] = {}

    def recording(name, fn):
        def step(b, f, o, s):
            out = fn(b, f, o, s)
            calls.setdefault(name, []).append((b, out))
            return out
        return step

    models = {m: recording(m, fn) for m, fn in twins().items()}
    net = MapNet(MapNetConfig(grid_shape=tuple(postmanip.grid.shape), width=8, embed=2, context=2, hidden=8,
                              levels=2)).eval()
    r = evaluate_rollouts(net, postmanip_dir, models=models, log=lambda _: None)
    assert set(r["final"]) == {"cnabu-map", "analytic-observation", "column-fill"}
    assert r["post_manipulation_scenes"] == 1
    assert r["effect_models"] == ANALYTIC_EFFECTS
    action, ws = postmanip.manipulation(2), postmanip.workspace
    for m in models:
        (_, out2), (in3, _) = calls[m][2], calls[m][3]
        want = predicted_belief(AnalyticPushEffect(), out2, action, ws)
        assert np.array_equal(in3.alpha, want.alpha), m
        assert np.array_equal(in3.eta, want.eta), m
        assert not np.array_equal(in3.alpha, out2.alpha), m  # the push changed the belief


def test_train_map_on_post_manipulation_data_records_the_effect_model(postmanip_dir, tmp_path):
    side = train_map(postmanip_dir, tmp_path / "m.pt", MapTrainConfig(batches=1, batch=1),
                     MapNetConfig(grid_shape=(78, 40, 30), width=8, embed=2, context=2, hidden=8, levels=2),
                     log=lambda _: None)
    assert side["post_manipulation_scenes"] == 1
    assert side["effect_models"] == ANALYTIC_EFFECTS
    assert side["train"]["effect_models"] == side["effect_models"]


def test_train_map_mixes_folders_of_different_sequence_lengths(postmanip_dir, tmp_path):
    """Two folders (12-view sequences, and 4 views with a push): every batch from one folder, both used."""
    side = train_map([HELDOUT, postmanip_dir], tmp_path / "m.pt", MapTrainConfig(batches=3, batch=1),
                     MapNetConfig(grid_shape=(78, 40, 30), width=8, embed=2, context=2, hidden=8, levels=2),
                     log=lambda _: None)
    assert side["data"]["scenes"] == 3
    assert side["data"]["folders"] == {str(HELDOUT): 2, str(postmanip_dir): 1}
    assert side["post_manipulation_scenes"] == 1
    from msmem_core.errors import UserError

    with pytest.raises(UserError, match="no folder holds a batch of 3"):
        train_map([HELDOUT, postmanip_dir], tmp_path / "n.pt", MapTrainConfig(batches=1, batch=3),
                  MapNetConfig(grid_shape=(78, 40, 30), width=8, embed=2, context=2, hidden=8, levels=2),
                  log=lambda _: None)


def test_the_shipped_network_settings_file_is_valid():
    from msmem_core.config import read_config_file

    arch = read_config_file(Path(__file__).parents[1] / "examples" / "train" / "cnabu-map-v2.yaml")
    cfg = MapNetConfig(**arch)
    assert cfg.class_head == "object"
    assert cfg.nearest_class


def test_the_object_head_class_loss_hardly_depends_on_the_occupancy():
    """Its class NLL is that of the object class given occupied: raising p on an occupied voxel
    barely changes it (only through the floors), where -log q_y would fall by log(p' / p)."""
    from msmem_cnabu.learn.maploss import map_loss

    occ = torch.ones(1, 2, 1, 1, dtype=bool)
    cls = torch.full((1, 2, 1, 1), 3).long()
    c = torch.zeros(1, 5, 2, 1, 1)
    c[0, 3] = 1.0
    c[0, 0] = -4.0
    valid = torch.ones(2, 1, 1, dtype=bool)

    def loss(o: float) -> float:
        oc = torch.full((1, 2, 1, 1), o)
        head = torch.cat([torch.nn.functional.logsigmoid(-oc)[:, None], torch.nn.functional.logsigmoid(oc)[:, None]
                          + torch.log_softmax(c[:, 1:], 1)], 1)  # the object head's log q
        return float(map_loss(oc, head, occ, cls, valid, 100.0, 300.0, occupied_only=True)[1])

    assert abs(loss(0.0) - loss(3.0)) < 0.02
    assert abs(loss(0.0) - loss(3.0)) < 0.05 * math.log((1 / (1 + math.exp(-3.0))) / 0.5)


def _log_q(p: np.ndarray, r: np.ndarray) -> torch.Tensor:
    """[1, C, N, 1, 1] log class probabilities ``[1 - p, p r]`` of per-voxel p [N] and object classes r [C-1, N]."""
    q = np.concatenate([(1 - p)[None], p[None] * r])
    return torch.log(torch.from_numpy(q))[None, :, :, None, None]


def test_a_class_is_known_from_the_belief_or_from_a_ray_that_hits_it():
    # 3 voxels, classes 0 (background) .. 3; voxel 0 occupied and class 1, voxel 1 free with class 2 on top
    r_prev = np.array([[0.5, 0.1, 0.3], [0.3, 0.8, 0.3], [0.2, 0.1, 0.4]])
    prev = _log_q(np.array([0.9, 0.2, 0.9]), r_prev)
    prev_logit = torch.logit(torch.tensor([0.9, 0.2, 0.9]))[None, :, None, None]
    valid = torch.ones(3, 1, 1, dtype=torch.bool)
    r_out = np.array([[0.3, 0.1, 0.2], [0.3, 0.1, 0.2], [0.4, 0.8, 0.6]])
    out = _log_q(np.array([0.9, 0.9, 0.9]), r_out)
    seen = torch.zeros(1, 4, 3, 1, 1, dtype=torch.bool)
    from msmem_cnabu.mapnet import known_object_classes

    # classes 1 and 3: top at an occupied voxel; class 2 tops only a free voxel
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, True]
    prev_logit[0, 2] = -1.0  # voxel 2 no longer believed occupied
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, False]
    seen[0, 3, 0] = True  # a ray hits class 3 where the new belief's top object class is 3
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, True]
    seen[0, 3, 0], seen[0, 2, 2] = False, True  # a hit of class 2 where the new belief says class 3
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, False]
    seen[0, 2, 2], seen[0, 3, 1] = False, True  # a hit of class 3 where the new belief says class 3 ...
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, True]
    valid[1] = False  # ... on a board voxel names nothing
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, True, False, False]
    valid[0] = False  # nor does a board voxel believed occupied
    assert known_object_classes(prev_logit, prev, out, seen, valid)[0].tolist() == [False, False, False, False]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1e-4, 1.0))
def test_restricting_classes_keeps_the_occupancy_and_the_known_classes_ratios(seed, weight):
    from msmem_cnabu.mapnet import restrict_classes

    g = torch.Generator().manual_seed(seed)
    logits = 3 * torch.randn(1, 5, 4, 2, 2, generator=g)
    known = torch.tensor([[False, True, False, True, False]])
    out = restrict_classes(logits, known, weight).exp()
    q = torch.softmax(logits, 1)
    assert torch.allclose(out.sum(1), torch.ones(()), atol=1e-5)
    assert torch.allclose(out[:, 0], q[:, 0], atol=1e-5)  # background, hence the occupancy, unchanged
    assert torch.allclose(out[:, 1] / out[:, 3], q[:, 1] / q[:, 3], rtol=1e-4)  # known classes keep their ratio
    assert torch.allclose(out[:, 2] / out[:, 1], weight * q[:, 2] / q[:, 1], rtol=1e-3)  # unknown ones scaled
    none = restrict_classes(logits, torch.zeros_like(known), weight).exp()
    assert torch.allclose(none, q, atol=1e-5)  # nothing known: nothing restricted


def test_the_restriction_removes_a_class_no_ray_showed_from_the_map(shard):
    net = MapNet(MapNetConfig(grid_shape=tuple(shard.grid.shape), class_head="object"))
    torch.manual_seed(0)
    with torch.no_grad():
        for prm in net.head[-1].parameters():
            prm.normal_(0, 0.5)  # a network that guesses classes everywhere
    seq = sequence(shard)
    valid = torch.from_numpy(seq.valid)
    steps, first = {}, {}
    for w in (1.0, 1e-3):
        b = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
        for t in range(3):
            with torch.no_grad():
                a, bb, e = net.step(*(torch.from_numpy(x)[None] for x in (b.alpha, b.beta, b.eta, seq.free[t],
                                                                             seq.occ[t], seq.seen[t])), valid, w)
            b = EvidentialMap(b.grid, a[0].numpy(), bb[0].numpy(), e[0].numpy())
            first.setdefault(w, b)
        steps[w] = b
    hit = np.flatnonzero(seq.seen[:3, 1:].any(axis=(0, 2, 3, 4))) + 1
    q = steps[1e-3].class_probs()
    occ = steps[1e-3].expected_occupancy() > 0.5
    named = np.unique(np.argmax(q[1:], 0)[occ & seq.valid] + 1)
    assert set(named) <= set(hit.tolist())  # only classes a ray showed are named
    q1 = steps[1.0].class_probs()
    assert not set(np.unique(np.argmax(q1[1:], 0)[(steps[1.0].expected_occupancy() > 0.5) & seq.valid] + 1)) <= set(
        hit.tolist())  # without it the guessing network names others
    # a step's occupancy is unchanged (later steps differ: the classes are the next step's input)
    np.testing.assert_allclose(first[1e-3].expected_occupancy(), first[1.0].expected_occupancy(), atol=1e-5)


def test_cnabu_map_keeps_the_ray_record_and_ups_finds_hidden_space_on_its_completed_belief(shard):
    import dataclasses

    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel
    from msmem_push.skill import PushSkill

    seq = sequence(shard)
    # unlabelled objects as ties of the network's evidence: every voxel no ray reached is confident
    model = CNABUMapObservationModel(CNABUMapConfig(unknown_evidence="tie"))
    b = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
    reached = np.zeros(shard.grid.shape, dtype=bool)
    for t in range(3):
        b = model.update_masks(b, seq.free[t], seq.occ[t], seq.seen[t])
        reached |= seq.free[t] | seq.occ[t] | seq.seen[t].any(axis=0)
        np.testing.assert_array_equal(b.observed, reached)  # the union of every view's rays, nothing else
    completed = (b.expected_occupancy() > 0.9) & ~b.observed
    assert completed.sum() > 1000  # confident voxels no ray reached: the completion
    assert b.never_seen(0.9)[completed].all()  # never seen, though confident
    rng = np.random.default_rng(0)
    assert len(PushSkill().sample(b, shard.workspace.shelf, rng)) > 0
    # read from the vacuity instead, the completed belief has nothing hidden: no push at all
    blind = dataclasses.replace(b, observed=None)
    assert not blind.never_seen(0.9)[completed].any()
    assert PushSkill().sample(blind, shard.workspace.shelf, np.random.default_rng(0)) == []


# ------------------------------------------------------------------------------ class map
def test_a_class_map_feeds_the_network_the_mapped_classes_and_maps_its_answer_back(shard):
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    f0, o0, s0 = start_masks(shard)
    b0 = AnalyticObservationModel().apply_masks(EvidentialMap.empty(shard.grid), f0, o0, s0)
    f, o, s = shard.masks(0)
    # the fill under surfaces takes the top voxel's class among the classes the belief holds: the unmapped
    # twin could take one the scene does not have, so both leave it out here; the mapped twin keeps the
    # network's guesses and their evidence (``unlabelled_columns``, ``unreached_occupied``: not by default)
    plain = CNABUMapObservationModel(CNABUMapConfig(unlabelled_objects="keep", fill_under_surfaces=None))
    keep = np.random.default_rng(0).permutation(np.arange(1, 15))[:11]  # scene class i is trained class keep[i-1]
    cmap = {f"thing{i}": plain.classes[k] for i, k in enumerate(keep, 1)}
    mapped = CNABUMapObservationModel(CNABUMapConfig(class_map=cmap, unlabelled_objects="keep",
                                                     fill_under_surfaces=None, unlabelled_columns="keep",
                                                     unreached_occupied="keep"))
    assert mapped.classes == ("background", *cmap)
    idx = np.r_[0, keep]
    unmapped = np.setdiff1d(np.arange(15), idx)
    eta, seen = b0.eta.copy(), s.copy()
    eta[unmapped], seen[unmapped] = 1.0, False  # what the scene cannot say about classes it does not have
    want = plain.update_masks(EvidentialMap(b0.grid, b0.alpha, b0.beta, eta, b0.observed), f, o, seen)
    got = mapped.update_masks(EvidentialMap(b0.grid, b0.alpha, b0.beta, b0.eta[idx].copy(), b0.observed),
                              f, o, s[idx])
    assert got.num_classes == 12
    np.testing.assert_array_equal(got.alpha, want.alpha)
    np.testing.assert_array_equal(got.beta, want.beta)
    np.testing.assert_array_equal(got.eta, want.eta[idx])


# a bad class map's one-line refusals, for every learned model: tests/test_class_map.py


def test_known_classes_from_rays_keeps_only_the_classes_this_episodes_rays_labelled(shard):
    """``known_classes: rays``: the classes a ray of the episode labelled, collected view by view and
    started afresh with an episode's first view (an empty belief); a network that guesses classes
    everywhere names no other."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    model = CNABUMapObservationModel(CNABUMapConfig(unseen_class_weight=1e-3, known_classes="rays",
                                                            unlabelled_objects="keep"))
    model.net = MapNet(MapNetConfig(grid_shape=tuple(shard.grid.shape), class_head="object"))
    torch.manual_seed(0)
    with torch.no_grad():
        for prm in model.net.head[-1].parameters():
            prm.normal_(0, 0.5)  # a network that guesses classes everywhere
    seq = sequence(shard)

    def named(b: EvidentialMap) -> set[int]:
        occ = (b.expected_occupancy() > 0.5) & seq.valid
        return set((np.unique(np.argmax(b.class_probs()[1:], 0)[occ]) + 1).tolist())

    b = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
    for t in range(3):
        b = model.update_masks(b, seq.free[t], seq.occ[t], seq.seen[t])
    hit = set((np.flatnonzero(seq.seen[:3, 1:].any(axis=(0, 2, 3, 4))) + 1).tolist())
    assert len(hit) > 1
    assert named(b) <= hit
    # a new episode: its first view shows one class only; the classes of the episode before are not known
    only = min(hit)
    seen = np.zeros_like(seq.seen[0])
    seen[only] = seq.seen[0][only]
    fresh = model.update_masks(EvidentialMap.empty(shard.grid, seq.seen.shape[1]), seq.free[0], seq.occ[0], seen)
    assert named(fresh) <= {only}


def test_restrict_state_false_restricts_the_returned_belief_and_keeps_the_networks_own_map(shard):
    """``restrict_state: false``: the belief returned is the restricted one, but the network's next input
    is its unrestricted map, so the returned occupancy and the state follow the unrestricted model
    view by view; a belief the model did not return (a copy: an effect model's prediction) is taken as
    it is, as with ``restrict_state: true``."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    def model(**kw):  # type: ignore[no-untyped-def]
        # the network's own map and what it returns (the ray record's authority is tested on its own below)
        m = CNABUMapObservationModel(CNABUMapConfig(**{"unlabelled_objects": "keep", "observed_voxels": "network",
                                                       **kw}))
        torch.manual_seed(0)  # the same network for every model (whatever ran before in the process)
        m.net = MapNet(MapNetConfig(grid_shape=tuple(shard.grid.shape), class_head="object"))
        with torch.no_grad():
            for prm in m.net.head[-1].parameters():
                prm.normal_(0, 0.5)  # a network that guesses classes everywhere
        return m

    restricted = {"unseen_class_weight": 1e-3, "known_classes": "rays"}
    own, fed, free_run = model(**restricted, restrict_state=False), model(**restricted), model()
    seq = sequence(shard)
    empty = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
    b_own, b_fed, b_free = empty, empty, empty
    for t in range(3):
        b_own = own.update_masks(b_own, seq.free[t], seq.occ[t], seq.seen[t])
        b_fed = fed.update_masks(b_fed, seq.free[t], seq.occ[t], seq.seen[t])
        b_free = free_run.update_masks(b_free, seq.free[t], seq.occ[t], seq.seen[t])
        for mine, unrestricted in zip(own._state[1], (b_free.alpha, b_free.beta, b_free.eta), strict=True):
            assert np.allclose(mine, unrestricted, atol=1e-5)
        assert np.allclose(b_own.expected_occupancy(), b_free.expected_occupancy(), atol=1e-5)
    assert not np.allclose(b_own.class_probs(), b_free.class_probs(), atol=1e-3)  # the output is restricted
    assert not np.allclose(b_own.class_probs(), b_fed.class_probs(), atol=1e-3)  # fed back, the maps part
    copy = EvidentialMap(b_fed.grid, b_fed.alpha.copy(), b_fed.beta.copy(), b_fed.eta.copy(), b_fed.observed)
    nxt_own = own.update_masks(copy, seq.free[3], seq.occ[3], seq.seen[3])
    nxt_fed = fed.update_masks(b_fed, seq.free[3], seq.occ[3], seq.seen[3])
    assert np.allclose(nxt_own.eta, nxt_fed.eta, atol=1e-5)


def test_unlabelled_objects_are_the_components_no_ray_labelled_with_their_class() -> None:
    """Three believed objects: one a ray labelled with its class somewhere (kept), one labelled only with
    another class (unlabelled), one never labelled (unlabelled); two touching objects of different
    classes are judged apart, and invalid voxels (the boards) are never objects."""
    from msmem_cnabu.mapmodel import unlabelled_objects

    shape, c = (12, 8, 6), 4
    occ = np.zeros(shape, dtype=bool)
    eta = np.ones((c, *shape), dtype=np.float32)
    for (x0, x1), k in (((0, 3), 1), ((3, 5), 2), ((8, 11), 3)):  # 1 and 2 touch
        occ[x0:x1, 2:5, 0:3] = True
        eta[k, x0:x1, 2:5, 0:3] = 9.0
    labelled = np.zeros((c, *shape), dtype=bool)
    labelled[1, 0, 2, 2] = True  # object 1, its class, one voxel
    labelled[1, 3, 2, 2] = True  # object 2, the wrong class
    valid = np.ones(shape, dtype=bool)
    out = unlabelled_objects(occ, eta, labelled, valid)
    assert not out[0:3].any()
    assert out[3:5, 2:5, 0:3].all()
    assert out[8:11, 2:5, 0:3].all()
    assert out.sum() == occ[3:5].sum() + occ[8:11].sum()
    valid[8:11] = False
    assert not unlabelled_objects(occ, eta, labelled, valid)[8:11].any()


def test_unlabelled_objects_unknown_abstains_in_the_output_and_keeps_the_networks_own_map(shard):
    """``unlabelled_objects: unknown``: the returned belief is the network's except on the objects no ray
    labelled, where the expected occupancy is 0.5 (a tie: free in the hard map) and the total evidence
    is kept; the network's next input stays its own map, so its state follows the plain model."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    from msmem_core.run.metrics import prediction_from_belief

    def model(**kw):  # type: ignore[no-untyped-def]
        # the network's own map and what it returns (the ray record's authority is tested on its own below)
        m = CNABUMapObservationModel(CNABUMapConfig(**{"unlabelled_objects": "keep", "observed_voxels": "network",
                                                       **kw}))
        torch.manual_seed(0)  # the same network for both models
        m.net = MapNet(MapNetConfig(grid_shape=tuple(shard.grid.shape), class_head="object"))
        with torch.no_grad():
            for prm in m.net.head[-1].parameters():
                prm.normal_(0, 0.5)  # a network that guesses objects and classes everywhere
        return m

    drop, plain = model(unlabelled_objects="unknown"), model()
    tie = model(unlabelled_objects="unknown", unknown_evidence="tie")
    seq = sequence(shard)
    empty = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
    b_drop, b_plain, b_tie = empty, empty, empty
    for t in range(3):
        b_drop = drop.update_masks(b_drop, seq.free[t], seq.occ[t], seq.seen[t])
        b_plain = plain.update_masks(b_plain, seq.free[t], seq.occ[t], seq.seen[t])
        b_tie = tie.update_masks(b_tie, seq.free[t], seq.occ[t], seq.seen[t])
        for mine, plain_map in zip(drop._state[1], (b_plain.alpha, b_plain.beta, b_plain.eta), strict=True):
            assert np.allclose(mine, plain_map, atol=1e-5)
    p_drop, p_plain = b_drop.expected_occupancy(), b_plain.expected_occupancy()
    changed = ~np.isclose(p_drop, p_plain, atol=1e-6)
    assert changed.any(), "the guessing network predicts objects no ray labelled"
    assert np.all(p_drop[changed] == 0.5)
    # the default unknown_evidence: the prior there (nothing known of it); tie: the network's evidence split
    assert np.all(b_drop.alpha[changed] == 1.0)
    assert np.all(b_drop.beta[changed] == 1.0)
    assert np.all(b_drop.eta[:, changed] == 1.0)
    np.testing.assert_array_equal(b_tie.expected_occupancy(), p_drop)
    assert np.allclose((b_tie.alpha + b_tie.beta), (b_plain.alpha + b_plain.beta), rtol=1e-5)
    occ_drop, _ = prediction_from_belief(p_drop, b_drop.class_probs())
    occ_plain, _ = prediction_from_belief(p_plain, b_plain.class_probs())
    assert (occ_drop <= occ_plain).all()
    assert occ_drop.sum() < occ_plain.sum()
    labelled = np.zeros_like(seq.seen[0])
    for t in range(3):
        labelled |= seq.seen[t]
    from msmem_cnabu.mapmodel import unlabelled_objects

    expect = unlabelled_objects(p_plain > 0.5, b_plain.eta, labelled, drop.valid(b_plain).numpy())
    assert np.array_equal(changed, expect & ~np.isclose(p_plain, 0.5, atol=1e-6))


def test_the_networks_own_map_carries_through_a_manipulation_where_the_belief_is_unchanged(shard):
    """A belief the model did not return but made from the one it did (an effect model's prediction):
    the network's next input is its own map wherever every value is still the returned belief's, and the
    given belief where the prediction changed it. Without the carry the returned abstentions (p = 0.5)
    would be the network's input everywhere."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    def model(**kw):  # type: ignore[no-untyped-def]
        # the network's own map and what it returns (the ray record's authority is tested on its own below)
        m = CNABUMapObservationModel(CNABUMapConfig(**{"unlabelled_objects": "keep", "observed_voxels": "network",
                                                       **kw}))
        torch.manual_seed(0)
        m.net = MapNet(MapNetConfig(grid_shape=tuple(shard.grid.shape), class_head="object"))
        with torch.no_grad():
            for prm in m.net.head[-1].parameters():
                prm.normal_(0, 0.5)
        return m

    drop, plain = model(unlabelled_objects="unknown"), model()
    seq = sequence(shard)
    b = EvidentialMap.empty(shard.grid, seq.seen.shape[1])
    for t in range(2):
        b = drop.update_masks(b, seq.free[t], seq.occ[t], seq.seen[t])
    sa, sb, se = (x.copy() for x in drop._state[1])
    assert not np.allclose(b.alpha, sa), "the returned belief abstains somewhere"
    moved = np.zeros(b.alpha.shape, dtype=bool)
    moved[20:40, 5:20, :10] = True  # the region a push changed: reset to the prior
    pred = EvidentialMap(b.grid, np.where(moved, 1.0, b.alpha).astype(np.float32),
                         np.where(moved, 1.0, b.beta).astype(np.float32),
                         np.where(moved[None], 1.0, b.eta).astype(np.float32), b.observed)
    nxt = drop.update_masks(pred, seq.free[2], seq.occ[2], seq.seen[2])
    expect_in = EvidentialMap(b.grid, np.where(moved, pred.alpha, sa), np.where(moved, pred.beta, sb),
                              np.where(moved[None], pred.eta, se), b.observed)
    ref = plain.update_masks(expect_in, seq.free[2], seq.occ[2], seq.seen[2])
    for mine, theirs in zip(drop._state[1], (ref.alpha, ref.beta, ref.eta), strict=True):
        assert np.allclose(mine, theirs, atol=1e-5)
    naive = plain.update_masks(pred, seq.free[2], seq.occ[2], seq.seen[2])
    assert not np.allclose(drop._state[1][0], naive.alpha, atol=1e-3)
    assert nxt.observed is not None


# ------------------------------------------------------------------------------ ray evidence is authoritative
def test_what_rays_reached_comes_from_the_rays_and_the_network_predicts_the_rest(shard):
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    views = [start_masks(shard), *(shard.masks(i) for i in range(4))]
    fused = CNABUMapObservationModel(CNABUMapConfig(fill_under_surfaces=None, ray_classes_within=None))
    net = CNABUMapObservationModel(CNABUMapConfig(observed_voxels="network"))
    rays = AnalyticObservationModel()
    b = n = r = EvidentialMap.empty(shard.grid)
    for f, o, s in views:
        b, n, r = fused.update_masks(b, f, o, s), net.update_masks(n, f, o, s), rays.apply_masks(r, f, o, s)
    labelled = r.eta.sum(axis=0) > r.num_classes
    p = r.expected_occupancy()
    leaning = p != 0.5
    assert labelled.sum() > 10000
    np.testing.assert_array_equal(b.eta[:, labelled], r.eta[:, labelled])  # the rays' classes, never overwritten
    np.testing.assert_array_equal(b.alpha[leaning], r.alpha[leaning])
    np.testing.assert_array_equal(b.beta[leaning], r.beta[leaning])
    never = ~b.observed
    assert never.sum() > 10000
    np.testing.assert_array_equal(b.alpha[never], n.alpha[never])  # the network's prediction where no ray went
    np.testing.assert_array_equal(b.eta[:, never], n.eta[:, never])
    # the network alone overwrites classes the rays labelled (what the rule is there for)
    assert (np.argmax(n.eta[:, labelled], axis=0) != np.argmax(r.eta[:, labelled], axis=0)).sum() > 100


def test_disturbed_rays_cap_keeps_a_disturbed_region_capped_through_the_next_view(shard):
    """MSAS caps the belief's evidence where a manipulation disturbed the shelf and tells the model
    (``ObservationModel.disturbed``). The ray record is authoritative where it is confident: with
    ``disturbed_rays: keep`` (the default) the next update restores the pre-manipulation evidence
    wherever the view's rays do not reach, and one view that sees such a voxel free overturns only
    57 % of them; with ``cap`` the region stays at the cap and that view overturns them all."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    def replay(mode: str) -> tuple[EvidentialMap, EvidentialMap, np.ndarray]:
        model = CNABUMapObservationModel(CNABUMapConfig(disturbed_rays=mode))
        b = EvidentialMap.empty(shard.grid, len(model.classes))
        for f, o, s in [start_masks(shard), *(shard.masks(i) for i in range(3))]:
            b = model.update_masks(b, f, o, s)
        total = model._rays.alpha + model._rays.beta
        region = np.zeros(b.alpha.shape, dtype=bool)
        region[total > 6.0] = True  # the voxels the rays are most sure of
        b = b.capped(region, 4.0)
        model.disturbed(region, 4.0)
        f, o, s = shard.masks(3)
        after = model.update_masks(b, f, o, s)
        p, c = model._rays.expected_occupancy(), model.config.ray_confidence
        unreached = region & ~(f | o | s.any(axis=0)) & ((p > c) | (p < 1 - c))  # where the record rules
        # then a view that sees the region free (as if what stood there was pushed away)
        gone = model.update_masks(after, region, np.zeros_like(region), np.zeros_like(s))
        return after, gone, unreached & (model._rays.alpha > 1.0)

    capped, capped_gone, unreached = replay("cap")
    kept, kept_gone, _ = replay("keep")
    assert unreached.sum() > 1000
    assert np.all((capped.alpha + capped.beta)[unreached] <= 4.0 + 1e-4)
    assert np.mean((kept.alpha + kept.beta)[unreached] > 6.0) > 0.99  # the record restored them
    occupied_before = unreached & (kept.expected_occupancy() > 0.5)
    assert occupied_before.sum() > 1000
    assert np.mean(capped_gone.expected_occupancy()[occupied_before] < 0.5) > 0.99
    assert np.mean(kept_gone.expected_occupancy()[occupied_before] < 0.5) < 0.8  # measured 0.57


@pytest.mark.parametrize(("mode", "after_success", "after_failure"),
                         [("keep", False, False), ("cap", True, True), ("failed", False, True)])
def test_disturbed_rays_decides_which_manipulations_cap_the_ray_record(shard, mode, after_success,
                                                                        after_failure):
    """``disturbed_rays``: ``cap`` caps the ray record after every manipulation, ``failed`` only after one
    that reported failure (``failed_manipulation``), ``keep`` never."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    model = CNABUMapObservationModel(CNABUMapConfig(disturbed_rays=mode))
    b = EvidentialMap.empty(shard.grid, len(model.classes))
    for f, o, s in [start_masks(shard), *(shard.masks(i) for i in range(2))]:
        b = model.update_masks(b, f, o, s)
    total = model._rays.alpha + model._rays.beta
    region = total > 6.0
    assert region.sum() > 1000
    for tell, capped in ((model.disturbed, after_success), (model.failed_manipulation, after_failure)):
        before = model._rays
        tell(region, 4.0)
        after = model._rays.alpha + model._rays.beta
        assert np.all(after[region] <= 4.0 + 1e-4) == capped
        assert np.array_equal(after[~region], (before.alpha + before.beta)[~region])


@pytest.mark.slow  # an option that is off by default
def test_an_occupied_voxel_no_ray_named_takes_the_class_of_the_nearest_voxel_rays_named(shard):
    """``ray_classes_within``: the network's completion of an object takes the object class of the nearest
    voxel whose rays gave one (within the distance), its object-class evidence moved onto that class; the
    rays' object classes, the background evidence and the occupancy are untouched."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel, majority_labels
    from scipy import ndimage

    views = [start_masks(shard), *(shard.masks(i) for i in range(4))]
    near = CNABUMapObservationModel(CNABUMapConfig(fill_under_surfaces=None, ray_classes_within=4))
    plain = CNABUMapObservationModel(CNABUMapConfig(fill_under_surfaces=None))  # the default: off
    rays = AnalyticObservationModel()
    b = n = r = EvidentialMap.empty(shard.grid)
    for f, o, s in views:
        b, n, r = near.update_masks(b, f, o, s), plain.update_masks(n, f, o, s), rays.apply_masks(r, f, o, s)
    np.testing.assert_array_equal(b.alpha, n.alpha)
    np.testing.assert_array_equal(b.beta, n.beta)
    np.testing.assert_array_equal(b.eta[0], n.eta[0])  # background evidence stays
    named = r.eta[1:].sum(axis=0) > r.num_classes - 1  # a ray gave these an object class
    np.testing.assert_array_equal(b.eta[:, named], n.eta[:, named])
    changed = (b.eta != n.eta).any(axis=0)
    source = majority_labels(r)[1:].any(axis=0)
    dist = ndimage.distance_transform_edt(~source)
    assert changed.sum() > 100
    assert (b.expected_occupancy()[changed] > 0.5).all()
    assert not named[changed].any()
    assert dist[changed].max() <= 4
    assert (b.eta[:, changed] >= 1.0).all()  # (the network's own evidence is 1 up to float rounding)
    # each took the majority class of a labelled voxel at its distance, with at least the network's mass
    cls = np.argmax(b.eta[1:], axis=0) + 1
    ray_cls = np.argmax(r.eta[1:], axis=0) + 1
    for x, y, z in np.argwhere(changed)[::37]:
        d = dist[x, y, z]
        lo, hi = np.maximum([x, y, z] - np.ceil(d).astype(int), 0), np.array([x, y, z]) + int(np.ceil(d)) + 1
        box = np.argwhere(source[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]) + lo
        at = box[np.isclose(np.linalg.norm(box - [x, y, z], axis=1), d)]
        assert cls[x, y, z] in {int(ray_cls[tuple(v)]) for v in at}
        mass = (n.eta[1:, x, y, z] - 1).sum()
        assert b.eta[1:, x, y, z].sum() - (b.num_classes - 1) == pytest.approx(max(mass, 1.0), rel=1e-5)
    # the network alone names some of these voxels otherwise
    assert (np.argmax(n.eta[1:, changed], axis=0) + 1 != cls[changed]).sum() > 10


def _replay(shard, views: int = 3, **kw: object) -> tuple[EvidentialMap, EvidentialMap]:
    """cnabu-map with ``kw`` through the shard's start view and ``views`` more (the scene's classes being
    the shard's first ones), and the ray record of the same views."""
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    model = CNABUMapObservationModel(CNABUMapConfig(**kw))
    idx = np.arange(len(model.classes))
    b = r = EvidentialMap.empty(shard.grid, len(model.classes))
    rays = AnalyticObservationModel()
    for f, o, s in [start_masks(shard), *(shard.masks(i) for i in range(views))]:
        b, r = model.update_masks(b, f, o, s[idx]), rays.apply_masks(r, f, o, s[idx])
    return b, r


def _some_class_map() -> dict[str, str]:
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    return {f"thing{i}": c for i, c in enumerate(CNABUMapObservationModel(CNABUMapConfig()).classes[1:12], 1)}


def test_unlabelled_columns_return_the_networks_guesses_where_no_ray_named_an_object_to_the_prior(shard):
    """``unlabelled_columns: unknown``: the voxels the network alone calls occupied, in the columns where no
    ray gave any voxel an object class, are the prior; nothing else changes. ``auto`` is that with a
    class map (the scene's objects are not the trained shapes) and ``keep`` without one."""
    keep, r = _replay(shard, unlabelled_columns="keep", fill_under_surfaces=None)  # (the fill fills under rays' hits)
    drop, _ = _replay(shard, unlabelled_columns="unknown", fill_under_surfaces=None)
    named = (r.eta[1:].sum(axis=0) > r.num_classes - 1).any(axis=2)
    reached = (r.alpha != 1.0) | (r.beta != 1.0)
    changed = (drop.alpha != keep.alpha) | (drop.beta != keep.beta) | (drop.eta != keep.eta).any(axis=0)
    assert changed.sum() > 1000
    assert not changed[named].any()
    assert not changed[reached].any()
    assert (drop.alpha[changed] == 1.0).all()
    assert (drop.beta[changed] == 1.0).all()
    assert (drop.eta[:, changed] == 1.0).all()
    # in those columns nothing no ray reached stays occupied
    assert not ((drop.expected_occupancy() > 0.5) & ~named[:, :, None] & ~reached).any()
    auto, _ = _replay(shard, fill_under_surfaces=None)
    np.testing.assert_array_equal(auto.alpha, keep.alpha)  # no class map: the network's guesses stay
    cmap = _some_class_map()
    mapped_auto, _ = _replay(shard, class_map=cmap, unreached_occupied="keep")
    mapped_drop, _ = _replay(shard, class_map=cmap, unlabelled_columns="unknown", unreached_occupied="keep")
    mapped_keep, _ = _replay(shard, class_map=cmap, unlabelled_columns="keep", unreached_occupied="keep")
    np.testing.assert_array_equal(mapped_auto.alpha, mapped_drop.alpha)
    np.testing.assert_array_equal(mapped_auto.eta, mapped_drop.eta)
    assert (mapped_auto.alpha != mapped_keep.alpha).sum() > 1000


def test_unreached_occupied_least_keeps_the_map_with_the_least_evidence(shard):
    """``unreached_occupied: least``: what no ray reached and the network calls occupied keeps the least
    evidence that calls it occupied (the hard maps, the classes and what rays reached are unchanged,
    its entropy is nearly the prior's); ``auto`` is that with a class map only."""
    from msmem_cnabu.mapmodel import LEAST_OCCUPIED_ALPHA

    keep, r = _replay(shard, views=2, unreached_occupied="keep", fill_under_surfaces=None)
    least, _ = _replay(shard, views=2, unreached_occupied="least", fill_under_surfaces=None)
    reached = (r.alpha != 1.0) | (r.beta != 1.0)
    np.testing.assert_array_equal(least.expected_occupancy() > 0.5, keep.expected_occupancy() > 0.5)
    np.testing.assert_array_equal(least.eta, keep.eta)
    changed = (least.alpha != keep.alpha) | (least.beta != keep.beta)
    assert changed.sum() > 1000
    assert not changed[reached].any()
    assert (least.alpha[changed] == LEAST_OCCUPIED_ALPHA).all()
    assert (least.beta[changed] == 1.0).all()
    assert (keep.expected_occupancy()[changed] > 0.6).mean() > 0.5  # the network was sure of most of them
    assert (least.expected_occupancy()[changed] < 0.55).all()
    auto, _ = _replay(shard, views=2, fill_under_surfaces=None)
    np.testing.assert_array_equal(auto.alpha, keep.alpha)  # no class map: the network's evidence
    cmap = _some_class_map()
    mapped_auto, _ = _replay(shard, views=2, class_map=cmap, fill_under_surfaces=None)
    mapped_keep, _ = _replay(shard, views=2, class_map=cmap, unreached_occupied="keep", fill_under_surfaces=None)
    assert (mapped_auto.alpha != mapped_keep.alpha).sum() > 1000
    assert ((mapped_auto.alpha == LEAST_OCCUPIED_ALPHA) | (mapped_auto.alpha == mapped_keep.alpha)).all()


@pytest.mark.slow
def test_a_predicted_change_hands_its_voxels_back_to_the_network_until_a_ray_reaches_them(shard):
    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.mapmodel import CNABUMapObservationModel

    model = CNABUMapObservationModel(CNABUMapConfig(fill_under_surfaces=None))
    f0, o0, s0 = start_masks(shard)
    b = model.update_masks(EvidentialMap.empty(shard.grid), f0, o0, s0)
    seen_occ = o0 & ~(shard.masks(0)[0] | shard.masks(0)[1])  # occupied in the start view, not in the next
    assert seen_occ.sum() > 100
    idx = np.flatnonzero(seen_occ)
    k = b.num_classes
    moved = BeliefDelta(idx, np.ones(len(idx), np.float32), np.ones(len(idx), np.float32),
                        np.ones((k, len(idx)), np.float32)).apply(b)  # an effect model: these voxels left
    assert not moved.observed[seen_occ].any()
    after = model.update_masks(moved, *shard.masks(0))
    stale = model._rays  # the record no longer holds the start view's hits there
    assert (stale.alpha[seen_occ] == 1).all()
    assert (stale.eta[:, seen_occ] == 1).all()
    assert not after.observed[seen_occ].any()


def test_ray_ties_network_lets_the_network_choose_among_tied_ray_classes_only():
    """``ray_ties: network``: a voxel whose rays gave classes 3 and 4 once each decodes as the network's
    choice between them (never as a third class the network prefers); untied voxels keep the rays'
    evidence exactly; evidence only grows, by at most the epsilon."""
    from msmem_cnabu.mapmodel import RAY_TIE_EPSILON, break_ray_ties

    c = 6
    ray = np.ones((c, 4, 1, 1), np.float32)
    ray[3, 0] = ray[4, 0] = 11.0  # tie, the network prefers 4 (and 5 above both)
    ray[3, 1] = ray[4, 1] = 11.0  # tie, the network prefers 3
    ray[2, 2] = 11.0  # one class: no tie
    # voxel 3: never labelled (all classes at the prior): no tie to break
    net = np.ones((c, 4, 1, 1), np.float32)
    net[4, 0], net[5, 0] = 5.0, 50.0
    net[3, 1], net[5, 1] = 5.0, 50.0
    net[5, 2] = 50.0
    net[1, 3] = 50.0
    eta = ray.copy()
    break_ray_ties(eta, ray, net)
    decoded = np.argmax(eta[1:], axis=0)[:, 0, 0] + 1
    assert decoded.tolist()[:3] == [4, 3, 2]
    assert np.array_equal(eta[:, 2:], ray[:, 2:])  # untied and unlabelled voxels: the rays' evidence as is
    assert np.array_equal(eta[[0, 1, 2, 5]], ray[[0, 1, 2, 5]])  # only the tied classes gain
    assert (eta >= ray).all()
    assert (eta - ray).sum(axis=0).max() <= RAY_TIE_EPSILON * (1 + 1e-6)
