"""The PTv3-style backbone and FE-vMF: curve encoders, permutation equivariance, attention confined to
patches (and crossing them over depth through shifts), the approach projection and the grasp pose."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from msmem_grasp.backbone import PointTransformer, hilbert_encode, morton_encode
from msmem_grasp.fevmf import FEVMF, FEVMFConfig, executable_grasp, project_approach

from msmem_core.world.gripper import GripperSpec

pytestmark = pytest.mark.usefixtures("one_torch_thread")
F64 = torch.float64


def _cube(n: int) -> torch.Tensor:
    return torch.stack(torch.meshgrid(*[torch.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)


def _cloud(n: int, seed: int = 0, exact_duplicates: bool = False) -> torch.Tensor:
    """Random points; a tenth of them share a 1 cm grid cell with another point (ties in the curve code)."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand((n, 3), generator=g, dtype=F64) * torch.tensor([0.4, 0.3, 0.2], dtype=F64)
    pts[: n // 10] = pts[n // 10 : 2 * (n // 10)] + (0.0 if exact_duplicates else 1e-7)
    return pts


# ------------------------------------------------------------------------------------ curve codes
@pytest.mark.parametrize(("bits", "encoder"), [(3, "hilbert"), (4, "hilbert"), (3, "morton"), (4, "morton")])
def test_curve_codes_are_a_bijection_of_the_cube(bits, encoder):
    cells = _cube(1 << bits)
    code = hilbert_encode(cells, bits) if encoder == "hilbert" else morton_encode(cells)
    assert torch.equal(torch.sort(code).values, torch.arange(len(cells)))


def test_codes_are_injective_at_10_bits():
    cells = torch.unique(torch.randint(0, 1024, (50_000, 3), generator=torch.Generator().manual_seed(0)), dim=0)
    for code in (hilbert_encode(cells), morton_encode(cells)):
        assert len(torch.unique(code)) == len(cells)
        assert int(code.min()) >= 0
        assert int(code.max()) < 1 << 30


@pytest.mark.parametrize("bits", [1, 2, 3, 4, 10])
def test_hilbert_neighbours_in_order_are_6_connected(bits):
    cells = _cube(min(1 << bits, 32))  # at 10 bits: the 32^3 corner sub-cube, which the curve fills first
    order = cells[torch.argsort(hilbert_encode(cells, bits))]
    steps = (order[1:] - order[:-1]).abs().sum(1)
    assert (steps == 1).all()


def test_morton_interleaves_x_y_z():
    cells = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1023, 1023, 1023], [2, 0, 0]])
    assert morton_encode(cells).tolist() == [4, 2, 1, (1 << 30) - 1, 32]


# ----------------------------------------------------------------------------------- equivariance
@pytest.mark.parametrize("in_features", [0, 2])
@pytest.mark.parametrize("exact_duplicates", [False, True])
def test_permuting_points_permutes_features(in_features, exact_duplicates):
    torch.manual_seed(0)
    model = PointTransformer(dim=32, layers=4, heads=4, patch_size=64, in_features=in_features).to(F64).eval()
    pts = _cloud(500, exact_duplicates=exact_duplicates)
    feats = torch.randn(500, in_features, dtype=F64) if in_features else None
    perm = torch.randperm(500, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        out = model(pts, feats)
        out_p = model(pts[perm], None if feats is None else feats[perm])
    assert out.shape == (500, 32)
    torch.testing.assert_close(out_p, out[perm], atol=1e-10, rtol=0)


# --------------------------------------------------------------------------------- patch locality
def _affected(model: PointTransformer, pts: torch.Tensor, i: int) -> torch.Tensor:
    """Points whose output changes when point i's input feature is perturbed."""
    feats = torch.zeros(len(pts), 1, dtype=F64)
    with torch.no_grad():
        base = model(pts, feats)
        feats[i] = 5.0
        moved = model(pts, feats)
    return (moved - base).abs().amax(1) > 1e-12


def _patch_of(model: PointTransformer, pts: torch.Tensor, i: int, layer: int = 0) -> torch.Tensor:
    layout = model.layouts(pts)[layer]
    members = layout.index[layout.slot[i] // model.patch_size]
    mask = torch.zeros(len(pts), dtype=torch.bool)
    mask[members[members < len(pts)]] = True
    return mask


def _model(**kw) -> PointTransformer:
    torch.manual_seed(0)
    return PointTransformer(dim=16, heads=2, in_features=1, patch_size=64, **kw).to(F64).eval()


def test_attention_stays_inside_its_patch():
    pts = _cloud(400)
    model = _model(layers=1, shift_patches=False)
    for i in (0, 123, 399):
        affected, patch = _affected(model, pts, i), _patch_of(model, pts, i)
        assert affected[i]
        assert int(affected.sum()) > 1
        assert not (affected & ~patch).any()  # ... and nothing else
    # the check can fail: one global patch (patch_size >= N) lets the perturbation reach everything
    torch.manual_seed(0)
    global_model = PointTransformer(dim=16, heads=2, in_features=1, patch_size=512, layers=1).to(F64).eval()
    assert (_affected(global_model, pts, 0) & ~_patch_of(model, pts, 0)).any()


def test_one_order_without_shift_never_crosses_patches_but_shifting_does():
    pts = _cloud(400)
    fixed = _model(layers=2, orders=("z",), shift_patches=False)
    shifted = _model(layers=2, orders=("z",), shift_patches=True)
    i = int(fixed.layouts(pts)[0].index[1, 60])  # a point near the end of patch 1
    patch = _patch_of(fixed, pts, i)
    assert not (_affected(fixed, pts, i) & ~patch).any()
    assert (_affected(shifted, pts, i) & ~patch).any()


def test_alternating_orders_mix_information_across_patches():
    pts = _cloud(400)
    model = _model(layers=2, shift_patches=False)  # z then hilbert
    assert (_affected(model, pts, 7) & ~_patch_of(model, pts, 7)).any()


def test_padded_slots_are_masked():
    # 6 points in one patch of 64 (58 padded slots) give what 6 points in a patch of 6 give
    pts = _cloud(6)
    torch.manual_seed(0)
    padded = PointTransformer(dim=16, heads=2, layers=2, patch_size=64).to(F64).eval()
    exact = PointTransformer(dim=16, heads=2, layers=2, patch_size=6, shift_patches=False).to(F64).eval()
    exact.load_state_dict(padded.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(padded(pts), exact(pts), atol=1e-12, rtol=0)


def test_a_batch_of_clouds_equals_the_clouds_alone():
    model = _model(layers=2)
    a, b = _cloud(150, seed=1), _cloud(90, seed=2) + 5.0
    fa, fb = torch.zeros(150, 1, dtype=F64), torch.ones(90, 1, dtype=F64)
    with torch.no_grad():
        out_a, out_b = model.forward_list([a, b], [fa, fb])
        torch.testing.assert_close(out_a, model(a, fa), atol=1e-12, rtol=0)
        torch.testing.assert_close(out_b, model(b, fb), atol=1e-12, rtol=0)


# --------------------------------------------------------------------------------------- FE-vMF
def test_fevmf_default_is_small_and_its_heads_are_in_range():
    model = FEVMF()
    assert model.num_parameters() < 500_000
    assert model.size_bytes() < 2 * 2**20
    pts = _cloud(300).float()
    out = model(pts)
    assert out.mu_a_hat.shape == out.mu_b.shape == (300, 3)
    torch.testing.assert_close(out.mu_a_hat.norm(dim=1), torch.ones(300))
    torch.testing.assert_close(out.mu_b.norm(dim=1), torch.ones(300))
    assert (out.kappa_a_hat >= model.config.kappa_floor).all()
    assert (out.kappa_b >= model.config.kappa_floor).all()
    assert (out.alpha >= 1).all()
    assert (out.beta >= 1).all()
    assert ((out.width > 0) & (out.width < 0.08)).all()
    assert ((out.uncertainty > 0) & (out.uncertainty <= 1)).all()
    a, kappa_a = out.approach()
    assert (a * out.mu_b).sum(1).abs().max() < 1e-5
    assert (kappa_a <= out.kappa_a_hat + 1e-6).all()


def test_fevmf_config_forbids_unknown_keys():
    with pytest.raises(ValueError, match="Extra inputs"):
        FEVMFConfig(dims=64)


def test_projection_follows_eq_proj():
    g = torch.Generator().manual_seed(0)
    a_hat = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=F64), dim=1)
    b = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=F64), dim=1)
    kappa = torch.rand(100, generator=g, dtype=F64) * 50
    a, kappa_a = project_approach(a_hat, b, kappa)
    torch.testing.assert_close((a * b).sum(1), torch.zeros(100, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(a.norm(dim=1), torch.ones(100, dtype=F64))
    sin = torch.linalg.cross(a_hat, b, dim=1).norm(dim=1)  # ||(I - b b^T) a_hat|| = sin(angle)
    torch.testing.assert_close(kappa_a, kappa * sin)
    assert ((a * a_hat).sum(1) >= -1e-12).all()  # the nearest direction orthogonal to b
    a_par = project_approach(b.clone(), b)  # degenerate: a_hat parallel to b
    assert torch.isfinite(a_par).all()
    assert (a_par * b).sum(1).abs().max() < 1e-12


def test_executable_grasp_matches_the_gripper_convention():
    contact = torch.tensor([[0.1, 0.2, 0.3]], dtype=F64)
    b = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64)
    a = torch.tensor([[0.0, 0.0, -1.0]], dtype=F64)  # top-down
    w = torch.tensor([0.04], dtype=F64)
    pose = executable_grasp(contact, a, b, w)[0]
    rot = pose[:3, :3]
    torch.testing.assert_close(rot.T @ rot, torch.eye(3, dtype=F64))
    assert torch.linalg.det(rot).item() == pytest.approx(1.0)
    torch.testing.assert_close(pose[:3, 3], torch.tensor([0.12, 0.2, 0.3], dtype=F64))
    torch.testing.assert_close(rot[:, 0], b[0])
    torch.testing.assert_close(rot[:, 2], a[0])
    torch.testing.assert_close(rot[:, 1], torch.linalg.cross(rot[:, 2], rot[:, 0]))  # y = z x x
    # the finger pads close on the two contacts: inner faces at -+ opening/2 along b
    left, right, _palm = GripperSpec().boxes(0.04)
    inner_left = pose[:3, :3].numpy() @ (left[0] + [left[1][0], 0, left[1][2]]) + pose[:3, 3].numpy()
    np.testing.assert_allclose(inner_left, contact[0].numpy(), atol=1e-12)
    assert right[0][0] > 0
    pose_np = executable_grasp(contact.numpy(), a.numpy(), b.numpy(), w.numpy())
    np.testing.assert_allclose(pose_np[0], pose.numpy(), atol=1e-12)
