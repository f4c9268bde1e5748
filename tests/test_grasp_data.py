"""FE-vMF training data: `generate_dataset` writes one consistent shard per scene, a rerun skips the
finished ones, a corrupt shard is named and regenerated (and named when training reads it), and one
training epoch on tiny data runs and lowers the loss."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from msmem_grasp.fevmf import FEVMFConfig
from msmem_grasp.fpp import FPPConfig
from msmem_grasp.learn.datagen import GraspDataConfig, ShardError, generate_dataset, load_shard, shard_path
from msmem_grasp.learn.training import TrainConfig, collate, train, validate

from msmem_core.run.executors import TaskFailure, run_tasks

TINY = GraspDataConfig(min_views=2, max_views=3, fpp=FPPConfig(num_points=768, ray_stride_px=8))
SEEDS = [11, 12]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("grasp-data")
    summary = generate_dataset(out, SEEDS, TINY, workers=1, progress=False, log=lambda m: None)
    assert not summary.failed, summary.failed
    return out, summary


@pytest.mark.slow  # data generation (about 16 s for the module's data set)
def test_each_scene_becomes_one_consistent_shard(dataset):
    out, summary = dataset
    assert sorted(g["seed"] for g in summary.generated) == SEEDS
    assert json.loads((out / "dataset.json").read_text())["seeds"] == SEEDS
    for seed in SEEDS:
        s = load_shard(shard_path(out, seed))
        n, p, g = len(s), len(s.positive_index), s.mask.shape[1]
        assert 0 < n <= 768
        assert 0 < p < n
        assert g == TINY.max_grasps
        assert s.points.shape == (n, 3)
        assert s.normals.shape == (n, 3)
        assert s.features().shape == (n, 4)
        assert s.approach.shape == s.baseline.shape == (p, g, 3)
        assert s.width.shape == (p, g)
        assert s.mask[:, 0].all()  # every positive has at least one GT grasp
        assert 2 <= len(s.views) <= 3
        assert s.seed == seed
        np.testing.assert_allclose(np.linalg.norm(s.baseline[s.mask], axis=1), 1.0, atol=2e-3)
        assert np.abs(np.einsum("ij,ij->i", s.approach[s.mask], s.baseline[s.mask])).max() < 5e-3
        assert (s.width[s.mask] > 0).all()
        assert (s.width[s.mask] <= 0.08 + 1e-6).all()
        assert len(np.unique(s.positive_index)) == p


@pytest.mark.slow  # data generation (about 16 s for the module's data set)
def test_a_rerun_skips_finished_shards(dataset):
    out, _ = dataset
    before = {s: shard_path(out, s).stat().st_mtime_ns for s in SEEDS}
    again = generate_dataset(out, SEEDS, TINY, workers=1, progress=False, log=lambda m: None)
    assert sorted(again.skipped) == SEEDS
    assert not again.generated
    assert not again.corrupt
    assert {s: shard_path(out, s).stat().st_mtime_ns for s in SEEDS} == before
    assert not list(out.glob(".*.tmp"))


@pytest.mark.slow  # data generation (about 16 s for the module's data set)
def test_a_corrupt_shard_is_named_then_regenerated(dataset, tmp_path):
    out, _ = dataset
    broken = tmp_path / "data"
    broken.mkdir()
    good = shard_path(out, SEEDS[0]).read_bytes()
    bad = shard_path(broken, SEEDS[0])
    bad.write_bytes(good[: len(good) // 2])  # a write cut off half-way
    with pytest.raises(ShardError, match=bad.name):
        load_shard(bad)
    with pytest.raises(ShardError, match="regenerate"):
        train(broken, tmp_path / "w.pt", TrainConfig(epochs=1), progress=False, log=lambda m: None)
    messages: list[str] = []
    summary = generate_dataset(broken, SEEDS[:1], TINY, workers=1, progress=False, log=messages.append)
    assert len(summary.corrupt) == 1
    assert bad.name in summary.corrupt[0]
    assert any(bad.name in m and "corrupt" in m for m in messages)
    assert load_shard(bad).seed == SEEDS[0]


def _explode(x: int) -> int:
    if x == 2:
        raise ValueError("boom")
    return x * 10


def test_run_tasks_keeps_order_and_reports_failures_without_stopping():
    res = run_tasks(_explode, [1, 2, 3], workers=1, progress=False)
    assert res[0] == 10
    assert res[2] == 30
    assert isinstance(res[1], TaskFailure)
    assert "ValueError: boom" in res[1].error


@pytest.mark.slow  # data generation (about 16 s for the module's data set)
def test_one_training_epoch_runs_and_lowers_the_loss(dataset, tmp_path):
    out, _ = dataset
    torch.manual_seed(0)
    small = FEVMFConfig(dim=16, layers=1, heads=2, patch_size=64, head_hidden=16, in_features=4)
    cfg = TrainConfig(epochs=1, val_fraction=0.0, lr=3e-3, warmup_steps=0, batch_scenes=1, threads=1, model=small)
    shards = [load_shard(shard_path(out, s)) for s in SEEDS]
    from msmem_grasp.fevmf import FEVMF

    torch.manual_seed(cfg.seed)
    before = validate(FEVMF(small), shards, 1.0, cfg.loss)["total"]
    side = train(out, tmp_path / "w.pt", cfg, progress=False, log=lambda m: None)
    from msmem_grasp.weights import load_fe_vmf

    after = validate(load_fe_vmf(tmp_path / "w.pt"), shards, 1.0, cfg.loss)["total"]
    assert math.isfinite(after)
    assert after < before
    assert side["epochs_run"] == 1
    assert len(side["sha256"]) == 64
    pts, feats, batch, targets = collate(shards)
    assert len(pts) == len(feats) == len(batch) == targets.num_points == sum(len(s) for s in shards)
