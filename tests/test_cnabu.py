"""Learned CNABU belief models: network invariants, exact copy of the prior outside the changed mask,
the evidential loss, data generation (valid shards, resume, corrupt shards), training and evaluation
end to end on tiny data, discoverable plugins selectable from config, and clear errors for bad weights.

Tiny everywhere: 2 cm voxels (a 39 x 20 x 15 grid), one or two scenes, one epoch."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from msmem_cnabu.configs import CNABUEffectConfig, CNABUObserveConfig
from msmem_cnabu.features import belief_features, grasp_regions, grid_interior, prior_evidence, wall_mask
from msmem_cnabu.learn.datagen import CNABUDataConfig, ShardError, generate_dataset, load_shard, shard_path
from msmem_cnabu.learn.losses import CNABULossConfig, cnabu_loss, dirichlet_kl_uniform
from msmem_cnabu.learn.training import TrainConfig, sha256_file, train, write_weights
from msmem_cnabu.models import CNABUGraspEffect, CNABUObservationModel, CNABUPushEffect
from msmem_cnabu.network import CNABUNet, CNABUNetConfig, flat_nonzero, parameter_bytes
from msmem_cnabu.weights import WeightsError, load_cnabu
from pydantic import ValidationError
from typer.testing import CliRunner

from msmem_core.errors import UserError
from msmem_core.interfaces import Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SHELF = ShelfSpec()
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.02, 1)
WORKSPACE = Workspace(GRID, SHELF)
NOLOG = lambda m: None  # noqa: E731


def random_belief(grid: GridSpec = GRID, seed: int = 0) -> EvidentialMap:
    rng = np.random.default_rng(seed)
    shape = tuple(grid.shape)
    return EvidentialMap(grid, rng.uniform(1, 30, shape).astype(np.float32),
                         rng.uniform(1, 30, shape).astype(np.float32),
                         rng.uniform(1, 20, (15, *shape)).astype(np.float32))


def tiny_net(kind: str, grid_shape=tuple(GRID.shape), change_bias: float | None = None, seed: int = 0) -> CNABUNet:
    torch.manual_seed(seed)
    net = CNABUNet(CNABUNetConfig(kind=kind, grid_shape=grid_shape, width=8, levels=2)).eval()
    with torch.no_grad():  # a non-trivial evidence head (it starts as the identity on the prior)
        for p in net.evidence[-1].parameters():
            p.normal_(0.0, 0.3)
        if change_bias is not None and net.change is not None:
            net.change.bias.fill_(change_bias)
    return net


# ------------------------------------------------------------------------------------------ network
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["observe", "push", "grasp"]),
    x=st.integers(3, 19), y=st.integers(3, 11), z=st.integers(1, 5), batch=st.integers(1, 2),
    levels=st.integers(1, 2), log_ev=st.floats(0.0, 6.0), seed=st.integers(0, 1000),
)
def test_network_shapes_and_evidence_at_least_one(kind, x, y, z, batch, levels, log_ev, seed):
    c = 4
    m = 2**levels
    assume(-(-x // m) * -(-y // m) >= 2)  # smaller grids are rejected (test_config_rejects_...)
    net = CNABUNet(CNABUNetConfig(kind=kind, grid_shape=(x, y, z), num_classes=c, width=4, levels=levels,
                                  context=2, hidden=8))
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    ev = lambda *s: 1.0 + torch.rand(*s, generator=g) * float(np.exp(log_ev))  # noqa: E731
    a, b, e = ev(batch, x, y, z), ev(batch, x, y, z), ev(batch, c, x, y, z)
    cfg = net.config
    act = (torch.rand(batch, cfg.action_voxel, x, y, z, generator=g) > 0.7).float()
    sc = torch.randn(batch, cfg.action_scalars, generator=g)
    with torch.no_grad():
        out = net(belief_features(a, b, e), prior_evidence(a, b, e), act, sc)
    assert out.alpha.shape == out.beta.shape == (batch, x, y, z)
    assert out.eta.shape == (batch, c, x, y, z)
    for t in (out.alpha, out.beta, out.eta):
        assert torch.isfinite(t).all()
        assert (t >= 1.0).all()
    if kind == "observe":
        assert out.change_logit is None
    else:
        assert out.change_logit.shape == (batch, x, y, z)
        assert ((out.change >= 0) & (out.change <= 1)).all()


def test_config_rejects_a_grid_too_small_for_its_levels():
    with pytest.raises(ValidationError, match=r"grid_shape.*levels=2"):
        CNABUNetConfig(kind="push", grid_shape=(3, 3, 2), levels=2)
    CNABUNetConfig(kind="push", grid_shape=(3, 5, 2), levels=2)  # a 1 x 2 coarsest map is enough


def test_default_network_is_small_and_starts_as_the_identity_on_the_prior():
    for kind in ("observe", "push", "grasp"):
        net = CNABUNet(CNABUNetConfig(kind=kind, width=TrainConfig().width))
        assert parameter_bytes(net) < 3_000_000
    net = CNABUNet(CNABUNetConfig(kind="push", grid_shape=tuple(GRID.shape), width=8, levels=2))
    b = random_belief()
    a, be, e = (torch.from_numpy(v)[None] for v in (b.alpha, b.beta, b.eta))
    with torch.no_grad():
        out = net(belief_features(a, be, e), prior_evidence(a, be, e), torch.zeros(1, 2, *GRID.shape),
                  torch.zeros(1, 4))
    torch.testing.assert_close(out.alpha, a)
    torch.testing.assert_close(out.eta, e)
    assert float(out.change.max()) < 0.1  # untrained: (almost) nothing changes


@settings(max_examples=40, deadline=None)
@given(shape=st.tuples(st.integers(1, 5), st.integers(1, 9), st.integers(1, 31)), density=st.floats(0.0, 1.0),
       runs=st.booleans(), seed=st.integers(0, 1000))
def test_flat_nonzero_equals_torch_nonzero(shape, density, runs, seed):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(shape, generator=g) < density
    if runs:  # clustered, as changed voxels are: whole rows of the last axis
        mask = mask[..., :1].expand(shape).contiguous()
    torch.testing.assert_close(flat_nonzero(mask), torch.nonzero(mask.reshape(-1)).squeeze(1), rtol=0, atol=0)


def test_batched_inference_matches_the_training_forward():
    net = tiny_net("push", change_bias=0.0)
    b = random_belief()
    a, be, e = (torch.from_numpy(v)[None] for v in (b.alpha, b.beta, b.eta))
    feats, prior = belief_features(a, be, e), prior_evidence(a, be, e)
    k = 3
    act = (torch.rand(k, 2, *GRID.shape) > 0.9).float()
    sc = torch.randn(k, 4)
    with torch.no_grad():
        full = net(feats.expand(k, -1, -1, -1, -1), prior.expand(k, -1, -1, -1, -1), act, sc)
    outs = net.predict_many(feats, prior, act, sc, threshold=0.5)
    for j, (idx, p, ev) in enumerate(outs):
        want = full.change[j].reshape(-1) > 0.5
        assert torch.equal(torch.sort(idx).values, torch.nonzero(want)[:, 0])
        torch.testing.assert_close(p, full.change[j].reshape(-1)[idx], rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(ev[:, 0], full.alpha[j].reshape(-1)[idx], rtol=1e-4, atol=1e-3)
        torch.testing.assert_close(ev[:, 2:], full.eta[j].reshape(15, -1)[:, idx].T, rtol=1e-4, atol=1e-3)


# ------------------------------------------------------------------------------------ belief models
def push_actions():
    from msmem_push.skill import PushAction

    return [PushAction(start_m=(x, 0.05), direction=(0.0, 1.0), length_m=0.12, height_m=0.02) for x in (-0.2, 0.1)] + [
        PushAction(start_m=(0.0, 0.1), direction=(0.6, 0.8), length_m=0.1, height_m=0.04)]


def grasp_actions():
    from msmem_grasp.skill import GraspAction

    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # approach down
    out = []
    for x in (-0.1, 0.15):
        pose[:3, 3] = (x, 0.15, 0.08)
        out.append(GraspAction(pose=tuple(map(tuple, pose)), width_m=0.05, opening_m=0.07,
                               contact_m=(x - 0.025, 0.15, 0.08),
                               target_class=3, retreat_m=((x, 0.15, 0.11), (x, -0.3, 0.11))))
    return out


def test_cnabu_grasp_believes_the_grasped_region_free_and_keeps_the_network_elsewhere(tmp_path):
    net = tiny_net("grasp", change_bias=0.3)
    w = tmp_path / "grasp.pt"
    write_weights(net, w)
    free = CNABUGraspEffect(CNABUEffectConfig(weights=w, change_threshold=0.5, batch=2))  # grasped_region: free
    raw = CNABUGraspEffect(CNABUEffectConfig(weights=w, change_threshold=0.5, batch=2, grasped_region="network"))
    belief = random_belief(seed=1)
    actions = grasp_actions()
    pred, net_pred = free.predict(belief, actions, WORKSPACE), raw.predict(belief, actions, WORKSPACE)
    assert pred.excluded is not None
    emptied = 0
    regions = grasp_regions(belief, actions, WORKSPACE)
    for k, (b, r) in enumerate(zip(pred.beliefs, net_pred.beliefs, strict=True)):
        region = np.asarray(regions[k])
        assert np.isin(region, pred.excluded[k]).all()  # the region is part of the intended removal
        emptied += len(region)
        assert np.all(b.alpha.reshape(-1)[region] == 1.0)
        assert np.all(b.beta.reshape(-1)[region] == 21.0)
        assert np.all(np.argmax(b.eta.reshape(b.num_classes, -1)[:, region], axis=0) == 0)
        rest = np.ones(GRID.size, dtype=bool)
        rest[region] = False
        np.testing.assert_array_equal(b.alpha.reshape(-1)[rest], r.alpha.reshape(-1)[rest])
        c = b.num_classes
        np.testing.assert_array_equal(b.eta.reshape(c, -1)[:, rest], r.eta.reshape(c, -1)[:, rest])
    assert emptied > 0


@pytest.mark.parametrize("kind", ["push", "grasp"])
def test_effect_model_copies_the_prior_exactly_outside_the_changed_mask(tmp_path, kind):
    net = tiny_net(kind, change_bias=0.3)  # roughly half the voxels pass the threshold
    w = tmp_path / f"{kind}.pt"
    write_weights(net, w)
    cls = CNABUPushEffect if kind == "push" else CNABUGraspEffect
    model = cls(CNABUEffectConfig(weights=w, change_threshold=0.5, batch=2, grasped_region="network"))
    belief = random_belief(seed=1)
    before = belief.copy()
    actions = push_actions() if kind == "push" else grasp_actions()
    pred = model.predict(belief, actions, WORKSPACE)
    walls = wall_mask(GRID, SHELF.interior_box)
    assert pred.changed.shape == (len(actions), *GRID.shape)
    assert len(pred.beliefs) == len(actions)
    for k, b in enumerate(pred.beliefs):
        ch = pred.changed[k]
        assert 0 < ch.sum() < GRID.size
        assert not (ch & walls).any()  # the boards never change
        out = ~ch
        assert np.array_equal(b.alpha[out], before.alpha[out])
        assert np.array_equal(b.beta[out], before.beta[out])
        assert np.array_equal(b.eta[:, out], before.eta[:, out])
        diff = (b.alpha != before.alpha) | (b.beta != before.beta) | np.any(b.eta != before.eta, axis=0)
        assert np.array_equal(diff, ch)  # exactly the voxels that differ
        assert np.array_equal(np.sort(pred.changes[k].idx), np.flatnonzero(ch.reshape(-1)))
        assert (b.alpha >= 1).all()
        assert (b.beta >= 1).all()
        assert (b.eta >= 1).all()
    assert np.array_equal(belief.alpha, before.alpha)  # the input is not modified
    if kind == "grasp":
        assert pred.excluded is not None
        assert len(pred.excluded) == len(actions)
    # a high threshold: nothing changes, the prediction is the prior itself
    none = cls(CNABUEffectConfig(weights=w, change_threshold=0.999, grasped_region="network")).predict(
        belief, actions, WORKSPACE)
    assert not none.changed.any()
    assert all(len(d.idx) == 0 for d in none.changes)


@pytest.mark.parametrize("quantile", [0.25, 0.75])
def test_change_epsilon_keeps_exactly_the_voxels_that_move_by_more_than_it(tmp_path, quantile):
    net = tiny_net("push", change_bias=0.3)
    w = tmp_path / "push.pt"
    write_weights(net, w)
    belief = random_belief(seed=3)
    actions = push_actions()
    full = CNABUPushEffect(CNABUEffectConfig(weights=w, change_threshold=0.5)).predict(belief, actions, WORKSPACE)
    p0, q0 = belief.expected_occupancy(), belief.class_probs()
    moves = [np.maximum(np.abs(b.expected_occupancy() - p0), np.abs(b.class_probs() - q0).max(0))
             for b in full.beliefs]
    epsilon = float(np.quantile(moves[0][full.changed[0]], quantile))  # some voxels on each side
    sparse = CNABUPushEffect(CNABUEffectConfig(weights=w, change_threshold=0.5, change_epsilon=epsilon)
                             ).predict(belief, actions, WORKSPACE)
    for k, (bf, bs) in enumerate(zip(full.beliefs, sparse.beliefs, strict=True)):
        want = full.changed[k] & (moves[k] > epsilon)
        # float32 rounding of the two means: ignore voxels within 1e-5 of the boundary
        edge = np.abs(moves[k] - epsilon) < 1e-5
        assert np.array_equal(sparse.changed[k] & ~edge, want & ~edge)
        keep = sparse.changed[k]  # kept voxels carry the full prediction, the rest the prior exactly
        assert np.array_equal(bs.alpha[keep], bf.alpha[keep])
        assert np.array_equal(bs.eta[:, keep], bf.eta[:, keep])
        assert np.array_equal(bs.alpha[~keep], belief.alpha[~keep])
        assert np.array_equal(bs.eta[:, ~keep], belief.eta[:, ~keep])
    assert 0 < sparse.changed[0].sum() < full.changed[0].sum()


def test_observation_model_changes_only_what_the_view_reached(tmp_path):
    w = tmp_path / "observe.pt"
    write_weights(tiny_net("observe"), w)
    model = CNABUObservationModel(CNABUObserveConfig(weights=w))
    belief = random_belief(seed=2)
    rng = np.random.default_rng(0)
    free = rng.random(GRID.shape) < 0.2
    occ = (rng.random(GRID.shape) < 0.05) & ~free
    seen = np.zeros((15, *GRID.shape), bool)
    seen[3] = occ
    new = model.update_masks(belief, free, occ, seen)
    reach = (free | occ) & ~wall_mask(GRID, grid_interior(GRID))
    diff = (new.alpha != belief.alpha) | (new.beta != belief.beta) | np.any(new.eta != belief.eta, axis=0)
    assert diff.any()
    assert not (diff & ~reach).any()
    assert (new.alpha >= 1).all()
    assert (new.eta >= 1).all()


# ------------------------------------------------------------------------------------------------ loss
def _synthetic_batch(seed: int = 0, shape=(8, 8, 4), c: int = 4, b: int = 2):
    g = torch.Generator().manual_seed(seed)
    gt_occ = torch.rand(b, *shape, generator=g) < 0.3
    gt_cls = torch.where(gt_occ, torch.randint(1, c, (b, *shape), generator=g), 0)
    return {
        "alpha": 1 + 10 * torch.rand(b, *shape, generator=g), "beta": 1 + 10 * torch.rand(b, *shape, generator=g),
        "eta": 1 + 5 * torch.rand(b, c, *shape, generator=g),
        "act_vox": (torch.rand(b, 2, *shape, generator=g) > 0.8).float(), "act_scalars": torch.randn(b, 4, generator=g),
        "gt_occ": gt_occ, "gt_cls": gt_cls, "change": torch.rand(b, *shape, generator=g) < 0.2,
        "valid": torch.ones(b, *shape, dtype=torch.bool), "focus": gt_occ,
    }


def test_loss_is_finite_even_for_extreme_evidence():
    d = _synthetic_batch()
    big = torch.full_like(d["alpha"], 1e5)
    one = torch.ones_like(d["alpha"])
    for a, b in ((big, one), (one, big), (one, one)):
        eta = torch.ones_like(d["eta"])
        eta[:, 1] = a
        terms = cnabu_loss(a, b, eta, torch.full_like(a, 30.0), a, b, eta, d["gt_occ"], d["gt_cls"], d["change"],
                           d["valid"], d["focus"], epoch=10.0)
        assert all(torch.isfinite(v) for v in terms.values())
    assert float(dirichlet_kl_uniform(torch.ones(1, 5))[0]) == pytest.approx(0.0, abs=1e-6)


def test_loss_decreases_when_overfitting_a_tiny_batch():
    torch.manual_seed(0)
    d = _synthetic_batch()
    net = CNABUNet(CNABUNetConfig(kind="push", grid_shape=(8, 8, 4), num_classes=4, width=8, levels=1, hidden=16))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    cfg = CNABULossConfig(anneal_epochs=1.0)
    feats, prior = belief_features(d["alpha"], d["beta"], d["eta"]), prior_evidence(d["alpha"], d["beta"], d["eta"])
    losses = []
    for _ in range(60):
        out = net(feats, prior, d["act_vox"], d["act_scalars"])
        terms = cnabu_loss(out.alpha, out.beta, out.eta, out.change_logit, d["alpha"], d["beta"], d["eta"],
                           d["gt_occ"], d["gt_cls"], d["change"], d["valid"], d["focus"], 1.0, cfg)
        assert torch.isfinite(terms["total"])
        opt.zero_grad()
        terms["total"].backward()
        opt.step()
        losses.append(float(terms["total"].detach()))
    assert losses[-1] < 0.75 * losses[0], losses[::10]
    assert losses[-1] < min(losses[:30]), losses[::10]


# ------------------------------------------------------------------------------- data, train, eval
TINY_PUSH = CNABUDataConfig(kind="push", voxel_m=0.02, min_views=1, max_views=2, states=1, actions_per_state=2)
TINY_OBSERVE = CNABUDataConfig(kind="observe", voxel_m=0.02, min_views=0, max_views=1, observe_samples=2)


@pytest.fixture(scope="module")
def push_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("cnabu-push")
    summary = generate_dataset(out, [3], TINY_PUSH, workers=1, progress=False, log=NOLOG)
    assert not summary.failed, summary.failed
    return out


@pytest.fixture(scope="module")
def observe_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("cnabu-observe")
    summary = generate_dataset(out, [4, 5], TINY_OBSERVE, workers=1, progress=False, log=NOLOG)
    assert not summary.failed, summary.failed
    return out


def test_push_datagen_writes_a_valid_shard(push_data):
    s = load_shard(shard_path(push_data, 3))
    shape = tuple(GRID.shape)
    assert s.kind == "push"
    assert s.seed == 3
    assert tuple(s.grid.shape) == shape
    assert len(s) == 2
    assert s.num_states == 1
    assert s.alpha.dtype == np.float16
    assert s.eta.shape == (1, 15, *shape)
    assert s.act_vox.shape == (2, 2, *shape)
    assert s.act_scalars.shape == (2, 4)
    assert s.gt_occ.shape == (2, *shape)
    assert s.gt_occ.any()
    assert s.act_vox[:, 0].any(axis=(1, 2, 3)).all()  # every push sweeps something
    b = s.belief(0)
    assert (b.alpha >= 1).all()
    assert (b.eta >= 1).all()
    a = s.action(0)
    assert a.kind == "push"
    assert np.isclose(np.hypot(*a.direction), 1.0)
    assert json.loads((push_data / "dataset.json").read_text())["config"]["kind"] == "push"
    again = generate_dataset(push_data, [3], TINY_PUSH, workers=1, progress=False, log=NOLOG)
    assert again.skipped == [3]
    assert not again.generated


def test_push_data_on_the_beliefs_of_another_observation_model(push_data, tmp_path):
    from msmem_core.plugins import ComponentRef

    cfg = TINY_PUSH.model_copy(update={"observation_model": ComponentRef(name="column-fill")})
    summary = generate_dataset(tmp_path, [3], cfg, workers=1, progress=False, log=NOLOG)
    assert not summary.failed, summary.failed
    filled, plain = load_shard(shard_path(tmp_path, 3)), load_shard(shard_path(push_data, 3))
    # the same scene and views; column-fill adds occupied evidence below what the rays saw
    assert np.array_equal(filled.gt_occ_before, plain.gt_occ_before)
    assert filled.state_view.tolist() == plain.state_view.tolist()
    assert filled.alpha.astype(float).sum() > plain.alpha.astype(float).sum()
    with pytest.raises(ValidationError, match="observe samples are the analytic ray masks"):
        CNABUDataConfig(kind="observe", observation_model=ComponentRef(name="cnabu-map"))


def test_observe_datagen_resumes_and_regenerates_a_corrupt_shard(observe_data):
    s = load_shard(shard_path(observe_data, 4))
    assert len(s) == 2
    assert s.num_states == 2
    assert s.act_vox.shape[1] == 17
    free, occ, _seen = s.masks(0)
    assert free.any()
    assert occ.any()
    assert not (free & occ).any()
    assert np.array_equal(s.gt_occ[0], s.gt_occ_before[0])  # a view moves nothing
    path = shard_path(observe_data, 5)
    data = bytearray(path.read_bytes())
    path.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(ShardError, match=str(path)):
        load_shard(path)
    logs = []
    again = generate_dataset(observe_data, [4, 5], TINY_OBSERVE, workers=1, progress=False, log=logs.append)
    assert again.skipped == [4]
    assert [g["seed"] for g in again.generated] == [5]
    assert len(again.corrupt) == 1
    assert load_shard(path).seed == 5
    with pytest.raises(Exception, match="push"):  # one folder, one kind
        generate_dataset(observe_data, [6], TINY_PUSH, workers=1, progress=False, log=NOLOG)


def test_train_and_eval_end_to_end_on_tiny_push_data(push_data, tmp_path):
    from msmem_core.cli import build_app

    app = build_app()
    out = tmp_path / "cnabu_push.pt"
    runner = CliRunner()
    res = runner.invoke(app, ["train", "cnabu", "--kind", "push", "--data", str(push_data), "--out", str(out),
                              "--epochs", "1", "--val-fraction", "0", "--threads", "1", "--width", "8", "-q"])
    assert res.exit_code == 0, res.output
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["kind"] == "push"
    assert side["sha256"] == sha256_file(out)
    assert side["epochs_run"] == 1
    assert np.isfinite(side["best"]["score"])
    net, meta = load_cnabu("push", out)
    assert meta["model"]["width"] == 8
    assert not net.training
    jpath = tmp_path / "eval.json"
    res = runner.invoke(app, ["eval", "belief-models", "--kind", "push", "--data", str(push_data),
                              "--weights", str(out),
                              "--threads", "1", "--candidates", "8", "--repeats", "1", "--json", str(jpath)])
    assert res.exit_code == 0, res.output
    r = json.loads(jpath.read_text())
    assert r["samples"] == 2
    for m in ("learned", "analytic", "no-change"):
        for region in ("affected", "all"):
            x = r["metrics"][m][region]
            keys = ("occ_nll", "occ_brier", "occ_ece", "sem_nll", "sem_brier", "sem_ece")
            assert all(np.isfinite(x[k]) for k in keys)
            assert 0 <= x["occ_brier"] <= 1
            assert 0 <= x["sem_brier"] <= 2
    assert r["changed_voxels_per_sample"]["no-change"] == 0
    t = r["timing"]
    assert t["simulate_and_remap_s"] > 0
    assert t["speedup_per_candidate"] > 0
    assert "speed-up" in res.output
    assert "| affected | learned |" in res.output


def test_fine_tuning_starts_from_the_init_weights(push_data, tmp_path):
    base = tmp_path / "base.pt"
    train("push", push_data, base, TrainConfig(epochs=1, val_fraction=0.0, threads=1, width=8),
          progress=False, log=NOLOG)
    start, _ = load_cnabu("push", base)
    tuned = tmp_path / "tuned.pt"
    logs: list[str] = []
    # width 16 is ignored: the architecture is the init's; a tiny lr keeps the weights near the start
    side = train("push", push_data, tuned, TrainConfig(epochs=1, val_fraction=0.0, threads=1, width=16, lr=1e-9,
                                                       init=str(base), seed=5), progress=False, log=logs.append)
    assert side["model"]["width"] == 8
    assert side["data"]["init"]["sha256"] == sha256_file(base)
    assert any("fine-tuning" in m for m in logs)
    net, _ = load_cnabu("push", tuned)
    fresh = tmp_path / "fresh.pt"
    train("push", push_data, fresh, TrainConfig(epochs=1, val_fraction=0.0, threads=1, width=8, lr=1e-9, seed=5),
          progress=False, log=NOLOG)
    other, _ = load_cnabu("push", fresh)
    a, b, c = start.state_dict(), net.state_dict(), other.state_dict()
    floats = [k for k in a if a[k].is_floating_point() and "running" not in k]
    assert max(float((a[k] - b[k]).abs().max()) for k in floats) < 1e-5
    assert max(float((a[k] - c[k]).abs().max()) for k in floats) > 1e-2  # without --init: a new network
    wrong = tmp_path / "wrong.pt"
    write_weights(CNABUNet(CNABUNetConfig(kind="push", grid_shape=(16, 8, 8), width=8)), wrong)
    with pytest.raises(UserError, match=r"--init .*wrong.pt: trained on a \(16, 8, 8\) grid"):
        train("push", push_data, tmp_path / "x.pt", TrainConfig(epochs=1, threads=1, init=str(wrong)),
              progress=False, log=NOLOG)


def test_train_and_eval_observe(observe_data, tmp_path):
    from msmem_cnabu.learn.evaluation import evaluate

    out = tmp_path / "cnabu_observe.pt"
    side = train("observe", observe_data, out, TrainConfig(epochs=1, val_fraction=0.5, threads=1, width=8),
                 progress=False, log=NOLOG)
    assert side["best"]["val"]["occ_nll"] > 0
    r = evaluate("observe", observe_data, out, threads=1, log=NOLOG, episodes=0)  # tiny grid: no episodes
    assert r["better_nll"] in ("learned", "analytic")
    a = r["metrics"]["analytic"]["affected"]
    n = r["metrics"]["no-change"]["affected"]
    assert a["occ_nll"] < n["occ_nll"]  # the analytic twin learns from the view; no-change does not


# ---------------------------------------------------------------------------------- plugins, weights
def test_plugins_are_discoverable_and_selectable_from_config(tmp_path):
    from msmem_core.config import load_config
    from msmem_core.plugins import ComponentRef, get_plugin_manager

    pm = get_plugin_manager()
    models = pm.belief_models()
    assert models["cnabu-observe"].roles == frozenset({"observe"})
    assert models["cnabu-push"].roles == models["cnabu-grasp"].roles == frozenset({"effect"})
    w = tmp_path / "p.pt"
    write_weights(tiny_net("push"), w)
    cfg_file = tmp_path / "run.yaml"
    cfg_file.write_text(f"skills:\n  - name: view\n  - name: push\n    effect_model:\n      name: cnabu-push\n"
                        f"      params: {{weights: {w}, change_threshold: 0.7}}\n")
    cfg = load_config("push-only", cfg_file)
    ref = next(s for s in cfg.skills if s.name == "push").effect_model
    model = pm.build("belief-model", ref, where="skills.1.effect_model")
    assert isinstance(model, CNABUPushEffect)
    assert model.config.change_threshold == 0.7
    with pytest.raises(WeightsError, match="msmem train cnabu --kind observe"):
        pm.build("belief-model", ComponentRef(name="cnabu-observe", params={"weights": str(tmp_path / "none.pt")}))


def test_bad_weights_raise_clear_errors(tmp_path):
    missing = tmp_path / "missing.pt"
    with pytest.raises(WeightsError) as e:
        load_cnabu("push", missing)
    assert str(missing) in str(e.value)
    assert "msmem datagen cnabu --kind push" in str(e.value)
    w = tmp_path / "w.pt"
    side = write_weights(tiny_net("push"), w)
    data = bytearray(w.read_bytes())
    data[len(data) // 2] ^= 0xFF
    w.write_bytes(bytes(data))
    with pytest.raises(WeightsError) as e:
        load_cnabu("push", w)
    assert str(w) in str(e.value)
    assert side["sha256"] in str(e.value)
    w.write_bytes(b"")
    with pytest.raises(WeightsError, match=side["sha256"]):
        load_cnabu("push", w)
    w2 = tmp_path / "w2.pt"
    write_weights(tiny_net("push"), w2)
    with pytest.raises(WeightsError, match="'push' weights"):
        load_cnabu("grasp", w2)
    meta = json.loads(w2.with_suffix(".json").read_text())
    meta["model"]["width"] = 16  # the hash matches, the tensors do not fit
    w2.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match="loading failed"):
        load_cnabu("push", w2)
    w2.with_suffix(".json").unlink()
    with pytest.raises(WeightsError, match="no sidecar"):
        load_cnabu("push", w2)
    w3 = tmp_path / "w3.pt"
    write_weights(tiny_net("push", grid_shape=(10, 10, 5)), w3)
    with pytest.raises(WeightsError, match="grid"):
        CNABUPushEffect(CNABUEffectConfig(weights=w3)).predict(random_belief(), push_actions(), WORKSPACE)


def test_a_config_names_shipped_weights_by_their_folder(tmp_path, monkeypatch):
    """``weights: msmem_cnabu/weights/NAME`` in a config is the shipped file from any working directory,
    unless such a relative file exists there."""
    from msmem_cnabu.weights import resolve_weights, shipped_weights

    monkeypatch.chdir(tmp_path)
    assert resolve_weights("msmem_cnabu/weights/cnabu_push.pt") == shipped_weights("push")
    _, meta = load_cnabu("push", "msmem_cnabu/weights/cnabu_push.pt")
    assert meta["sha256"] == json.loads(shipped_weights("push").with_suffix(".json").read_text())["sha256"]
    assert resolve_weights("other/weights/cnabu_push.pt") == Path("other/weights/cnabu_push.pt")
    local = tmp_path / "msmem_cnabu" / "weights" / "cnabu_push.pt"
    local.parent.mkdir(parents=True)
    local.write_bytes(b"")
    assert resolve_weights("msmem_cnabu/weights/cnabu_push.pt") == Path("msmem_cnabu/weights/cnabu_push.pt")


def test_dirichlet_kl_uniform_against_scipy_at_large_evidence_in_float32():
    """KL(Dir(eta) || Dir(1)) = -H(Dir(eta)) - log Gamma(C) (the uniform Dirichlet's density is Gamma(C))."""
    import math

    from msmem_cnabu.learn.losses import dirichlet_kl_uniform
    from scipy import stats

    for eta in ([2.0, 3.0, 4.0], [1e4, 2e4, 5.0], [7e4, 1.0, 1.0, 3e3]):
        e = torch.tensor([eta], dtype=torch.float32)
        want = -stats.dirichlet(eta).entropy() - math.lgamma(len(eta))
        assert float(dirichlet_kl_uniform(e)[0]) == pytest.approx(want, rel=1e-5, abs=1e-4)


@pytest.mark.slow  # 23 s: a hard scene needs several generator attempts (CI runs the slow tests too)
def test_datagen_require_hard_makes_hard_scenes(tmp_path):
    """`--require-hard` reaches the scene generator: the shard's scene is the hard one of its seed."""
    from msmem_core.cli import build_app
    from msmem_core.world.scenegen import SceneGenConfig, generate_scene

    res = CliRunner().invoke(build_app(), ["datagen", "cnabu", "--kind", "observe", "--scenes", "1", "--seed", "300000",
                                           "--samples", "1", "--min-views", "0", "--max-views", "0", "--require-hard",
                                           "--out", str(tmp_path), "-q"])
    assert res.exit_code == 0, res.output
    shard = load_shard(next(tmp_path.glob("scene_*.npz")))
    assert shard.info["config"]["require_hard"] is True
    from msmem_core.world.voxelize import voxelize

    for hard, match in ((True, True), (False, False)):
        occ, _ = voxelize(generate_scene(300000, SceneGenConfig(require_hard=hard)).objects, shard.grid)
        assert np.array_equal(occ, shard.gt_occ[0]) is match


def test_dirichlet_expected_ce_against_monte_carlo_and_the_misleading_evidence_kl():
    """psi(S) - psi(eta_y) is E[-log q_y] under Dir(eta) (scipy samples); the misleading-evidence KL
    is the KL of eta with the true class's evidence set to 1, on a [B, C, X] batch."""
    import scipy.stats
    from msmem_cnabu.learn.losses import blend, dirichlet_expected_ce, evidential_dirichlet_loss

    rng = np.random.default_rng(0)
    eta = np.array([[2.0, 5.0, 1.5], [1.0, 1.0, 9.0]])  # [B=2, C=3]
    y = np.array([1, 0])
    ce = dirichlet_expected_ce(torch.tensor(eta)[..., None], torch.tensor(y)[:, None])[:, 0].numpy()
    for b in range(2):
        q = scipy.stats.dirichlet(eta[b]).rvs(size=200_000, random_state=rng)
        mc = -np.log(q[:, y[b]]).mean()
        assert ce[b] == pytest.approx(mc, rel=0.01)
    got_ce, kl = evidential_dirichlet_loss(torch.tensor(eta)[..., None], torch.tensor(y)[:, None], 0.5)
    np.testing.assert_allclose(got_ce[:, 0].numpy(), ce)
    misleading = eta.copy()
    misleading[np.arange(2), y] = 1.0
    want = 0.5 * dirichlet_kl_uniform(torch.tensor(misleading)).numpy()
    np.testing.assert_allclose(kl[:, 0].numpy(), want, rtol=1e-12)
    assert kl[1, 0].item() > kl[0, 0].item() > 0  # more evidence on wrong classes, a larger penalty
    old, pred, p = torch.tensor([1.0, 4.0]), torch.tensor([3.0, 2.0]), torch.tensor([0.25, 0.5])
    np.testing.assert_allclose(blend(old, pred, p).numpy(), [1.5, 3.0])


def _loss_reference(a, b, eta, logit, pa, pb, peta, occ, cls, change, valid, focus, cfg, epoch):
    """cnabu_loss recomputed voxel by voxel in float64 with scipy: the KL of a Beta / Dirichlet to the
    uniform one is minus its differential entropy (minus log Gamma(C), the uniform Dirichlet's
    log density), scipy.stats' ``.entropy()``."""
    import math

    import scipy.special as sp
    import scipy.stats

    kl_w = cfg.kl_max * min(1.0, epoch / cfg.anneal_epochs)
    n_cls = eta.shape[1]
    acc = {"occ_ce": 0.0, "occ_kl": 0.0, "sem_ce": 0.0, "sem_kl": 0.0}
    wsum = bce_sum = vsum = 0.0
    for i in np.ndindex(*a.shape):
        p = 1.0 / (1.0 + math.exp(-logit[i])) if logit is not None else 1.0
        al = pa[i] * (1 - p) + a[i] * p
        be = pb[i] * (1 - p) + b[i] * p
        e = np.array([peta[(i[0], c, *i[1:])] * (1 - p) + eta[(i[0], c, *i[1:])] * p for c in range(n_cls)])
        w = float(valid[i]) * (1.0 + cfg.focus_weight * float(focus[i]))
        wsum += w
        y, k = float(occ[i]), int(cls[i])
        acc["occ_ce"] += w * (sp.digamma(al + be) - sp.digamma(al if y else be))
        at, bt = (1.0, be) if y else (al, 1.0)
        acc["occ_kl"] += w * kl_w * -scipy.stats.beta(at, bt).entropy()
        acc["sem_ce"] += w * (sp.digamma(e.sum()) - sp.digamma(e[k]))
        et = e.copy()
        et[k] = 1.0
        acc["sem_kl"] += w * kl_w * (-scipy.stats.dirichlet(et).entropy() - sp.gammaln(n_cls))
        if logit is not None:
            q = 1.0 / (1.0 + math.exp(-logit[i]))
            t = float(change[i])
            bce_sum += float(valid[i]) * -(cfg.change_pos_weight * t * math.log(q) + (1 - t) * math.log(1 - q))
            vsum += float(valid[i])
    out = {k: v / max(wsum, 1.0) for k, v in acc.items()}
    out["total"] = (cfg.w_occupancy * (out["occ_ce"] + out["occ_kl"])
                    + cfg.w_semantic * (out["sem_ce"] + out["sem_kl"]))
    if logit is not None:
        out["change_bce"] = bce_sum / max(vsum, 1.0)
        out["total"] += cfg.w_change * out["change_bce"]
    return out


@pytest.mark.parametrize("epoch", [2.0, 9.0])
@pytest.mark.parametrize("with_change", [True, False])
def test_cnabu_loss_against_a_voxelwise_scipy_reference(epoch, with_change):
    rng = np.random.default_rng(7)
    shape, c = (2, 3, 2, 2), 4
    ev = lambda *s: (1.0 + rng.gamma(1.5, 3.0, size=s)).astype(np.float64)  # noqa: E731
    a, b, pa, pb = ev(*shape), ev(*shape), ev(*shape), ev(*shape)
    eta, peta = ev(shape[0], c, *shape[1:]), ev(shape[0], c, *shape[1:])
    logit = rng.normal(0, 1.5, size=shape) if with_change else None
    occ = rng.random(shape) < 0.4
    cls = np.where(occ, rng.integers(1, c, size=shape), 0)
    change = rng.random(shape) < 0.3
    valid = rng.random(shape) < 0.8
    focus = rng.random(shape) < 0.35
    cfg = CNABULossConfig(w_occupancy=0.7, w_semantic=1.3, w_change=0.4, change_pos_weight=3.0,
                          focus_weight=2.5, anneal_epochs=4.0, kl_max=0.3)
    t = torch.from_numpy
    got = cnabu_loss(t(a), t(b), t(eta), None if logit is None else t(logit), t(pa), t(pb), t(peta), t(occ),
                     t(cls), t(change), t(valid), t(focus), epoch, cfg)
    ref = _loss_reference(a, b, eta, logit, pa, pb, peta, occ, cls, change, valid, focus, cfg, epoch)
    assert set(got) == set(ref)
    for k, v in ref.items():
        assert float(got[k]) == pytest.approx(v, rel=1e-9, abs=1e-12), k


def test_cnabu_loss_without_valid_voxels_is_zero_not_nan():
    shape, c = (1, 2, 2, 2), 3
    ones = torch.ones(shape, dtype=torch.float64)
    eta = torch.ones(1, c, *shape[1:], dtype=torch.float64) * 2.0
    none = torch.zeros(shape, dtype=torch.bool)
    got = cnabu_loss(ones * 3, ones, eta, torch.zeros(shape, dtype=torch.float64), ones, ones, eta, none,
                     torch.zeros(shape, dtype=torch.long), none, none, none, 1.0)
    assert all(float(v) == 0.0 for v in got.values())  # sums over no voxel divided by at least 1
