"""A geometric grasp predictor on the belief: the grasp skill's fallback when no trained FE-vMF
weights are installed. It outputs the same per-point evidential quantities as FE-vMF (a_hat, b with
concentrations, Beta affordance evidence, width), so FE-UMGF and everything downstream are the same.
It reads the belief only (expected occupancy), never ground truth.

At each FPP point c with outward normal n (the normal's z component below ``max_normal_z``: a
side face of an upright object; points on tops and undersides get no affordance):

- *Baseline*: b = -n flattened to the horizontal plane (object faces are vertical in a shelf).
- *Width*: marching from c along b in half-voxel steps, the first sample in a believed-free voxel
  (p < ``free_threshold``) ends the object; w = that distance minus 3/4 voxel (the far surface lies
  in the last non-free voxel). Where the far side was never seen at the contact's height (unknown
  space, p ~ 0.5, is not free), the march is repeated along the object's top layer, which cameras
  above the shelf see; if neither finds free space within the opening, no width, no affordance.
- *Antipodal*: the normal at c and the far contact's normal (negative occupancy gradient there)
  both lie within the friction cone (half-angle atan(``friction``)) of b.
- *Approach* (``approach: top-first``, the default): top-down (a_hat = -z) if the object's top
  above c (marching up from just inside c to free space) is ``min_depth_m``..``finger_length -
  clearance_m`` above c, so the fingers overlap the object without the palm touching its top, and
  the gripper with the lift fits under the shelf top; else from the front (a_hat = +y made
  orthogonal to b) if b is mostly across the shelf (|b_y| < 0.5) and c is within the same depth
  range behind the object's front face. With ``approach: front-first`` the front approach is taken
  wherever it is valid, top-down elsewhere (for an arm whose hand cannot come from above in the
  shelf).
- *Affordance*: quality 1 for a valid, antipodal width and approach (tapering to 0 as the width reaches the
  gripper's opening minus ``opening_margin_m``), else 0; evidence ``evidence * confidence`` with
  the confidence of the contact voxel (p from 0.5 to 0.9 -> 0 to 1): alpha = 1 + E q,
  beta = 1 + E (1 - q), as FE-vMF's softplus + 1.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.map.belief import EvidentialMap
from msmem_core.world.geometry import F64
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import ShelfSpec
from msmem_grasp.fpp import SurfaceCloud, _trilinear, occupancy_normals
from msmem_grasp.fusion import GraspHypotheses


class GeometricConfig(BaseModel):
    """Parameters of the geometric fallback predictor (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    free_threshold: float = Field(0.3, gt=0.0, lt=0.5)
    """Expected occupancy below which a voxel is believed free (one free view: p = 1/12)."""
    max_normal_z: float = Field(0.7, gt=0.0, le=1.0)
    """Points whose normal has a larger |z| (tops, undersides) are not contacts."""
    min_depth_m: float = Field(0.015, ge=0.0)
    """The fingers overlap the object by at least this much along the approach."""
    clearance_m: float = Field(0.01, ge=0.0)
    """Room kept between the palm and the object, and between the gripper and the shelf top."""
    opening_margin_m: float = Field(0.01, ge=0.0)
    """Widths above the maximal opening minus this get no affordance."""
    min_width_m: float = Field(0.015, ge=0.0)
    """Thinner parts (edges, handles) get no affordance."""
    lift_m: float = Field(0.03, ge=0.0)
    """The lift the skill performs (top-down grasps must leave room for it under the shelf top)."""
    evidence: float = Field(6.0, gt=0.0)
    """Beta evidence of a fully confident contact."""
    friction: float = Field(0.5, gt=0.0)
    """Coulomb coefficient of the antipodal test: both contact normals within atan(mu) of b."""
    normal_sigma_voxels: float = Field(1.0, gt=0.0)
    """Gaussian-derivative scale of the occupancy gradient the far contact's normal comes from."""
    kappa_b: float = Field(20.0, gt=0.0)
    """vMF concentration of b at a fully confident side-face contact (plus 1)."""
    kappa_a_hat: float = Field(8.0, gt=0.0)
    """vMF concentration of a_hat at a fully confident contact."""
    approach: Literal["top-first", "front-first"] = "top-first"
    """Which approach a contact valid for both gets: top-down or from the front."""


def _sample(p: NDArray[np.floating], grid: object, pts: F64) -> F64:
    """Expected occupancy of the voxel holding each point [..., 3]; in front of the grid (y below it,
    the open front of the shelf) it is free (0), elsewhere outside it occupied (1: the boards)."""
    ijk = grid.index_of(pts)  # type: ignore[attr-defined]
    shape = np.asarray(grid.shape)  # type: ignore[attr-defined]
    inside = np.all((ijk >= 0) & (ijk < shape), axis=-1)
    c = np.clip(ijk, 0, shape - 1)
    out = np.asarray(p, dtype=np.float64)[c[..., 0], c[..., 1], c[..., 2]]
    front = ijk[..., 1] < 0
    return np.where(inside, out, np.where(front, 0.0, 1.0))


def _first_free(p: NDArray[np.floating], grid: object, start: F64, direction: F64, length: float, step: float,
                threshold: float) -> tuple[F64, NDArray[np.bool_]]:
    """Distance from each start point along its direction to the first sample in a free voxel
    ([N]) and whether one was found within ``length``."""
    ts = np.arange(1, int(np.ceil(length / step)) + 1) * step
    pts = start[:, None, :] + ts[None, :, None] * direction[:, None, :]
    free = _sample(p, grid, pts) < threshold
    first = np.argmax(free, axis=1)
    return ts[first], free.any(axis=1)


def predict_geometric(
    belief: EvidentialMap, cloud: SurfaceCloud, shelf: ShelfSpec, gripper: GripperSpec,
    config: GeometricConfig | None = None,
) -> GraspHypotheses:
    """Per-point evidential grasps of the cloud from the belief's geometry (module docstring)."""
    cfg = config or GeometricConfig()
    n = len(cloud)
    if n == 0:
        return GraspHypotheses.empty()
    grid = belief.grid
    s = grid.voxel_m
    step = s / 2
    p = belief.expected_occupancy()
    c = cloud.points.astype(np.float64)
    nrm = cloud.normals.astype(np.float64)
    side = np.abs(nrm[:, 2]) < cfg.max_normal_z
    bh = -nrm.copy()
    bh[:, 2] = 0.0
    bh_n = np.linalg.norm(bh, axis=1, keepdims=True)
    b = np.where(side[:, None] & (bh_n > 1e-9), bh / np.maximum(bh_n, 1e-12), -nrm)
    b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)

    max_w = gripper.max_opening_m - cfg.opening_margin_m
    inner = c + step * b
    reach = gripper.finger_length_m - cfg.clearance_m
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), c.shape)
    t_top, top_found = _first_free(p, grid, inner, up, shelf.height_m, step, cfg.free_threshold)
    top = inner[:, 2] + t_top - step  # the object's top above the contact
    depth = top - c[:, 2]

    # the far side: at the contact's height, else (unseen there) along the object's top layer, which
    # cameras above the shelf see; the free sample lies 0-1 step beyond the boundary after the
    # far surface, which lies in the last non-free voxel (FPP puts c about on the near surface)
    t_free, found = _first_free(p, grid, c, b, max_w + s, step, cfg.free_threshold)
    top_layer = c.copy()
    top_layer[:, 2] = top - step
    t_free2, found2 = _first_free(p, grid, top_layer, b, max_w + s, step, cfg.free_threshold)
    use2 = ~found & found2 & top_found & (depth <= reach)
    t_free = np.where(use2, t_free2, t_free)
    found = found | use2
    width = np.clip(t_free - 0.5 * step - 0.5 * s, step, gripper.max_opening_m)
    width_ok = found & (width <= max_w) & (width >= cfg.min_width_m)
    # antipodal: both contact normals inside the friction cone around the baseline
    cos_cone = 1.0 / np.sqrt(1.0 + cfg.friction**2)
    grad = occupancy_normals(p, cfg.normal_sigma_voxels)
    far = np.where(use2[:, None], top_layer, c) + width[:, None] * b
    n_far = np.stack([_trilinear(grad[k], grid, far) for k in range(3)], axis=1)
    n_far /= np.maximum(np.linalg.norm(n_far, axis=1, keepdims=True), 1e-12)
    antipodal = (np.einsum("nk,nk->n", n_far, b) >= cos_cone) & (np.einsum("nk,nk->n", -nrm, b) >= cos_cone)
    width_ok &= antipodal
    length = gripper.finger_length_m + gripper.palm_depth_m
    top_ok = side & top_found & (depth >= cfg.min_depth_m) & (depth <= reach)
    top_ok &= c[:, 2] + length + cfg.lift_m + cfg.clearance_m <= shelf.height_m

    a_front = np.array([0.0, 1.0, 0.0]) - b[:, 1:2] * b
    a_front /= np.maximum(np.linalg.norm(a_front, axis=1, keepdims=True), 1e-12)
    t_front, front_found = _first_free(p, grid, inner, -a_front, reach + s, step, cfg.free_threshold)
    extent = t_front - step  # how far behind the object's front face the contact lies
    half_w = gripper.finger_width_m / 2
    front_ok = side & (np.abs(b[:, 1]) < 0.5) & front_found & (extent >= cfg.min_depth_m) & (extent <= reach)
    front_ok &= (c[:, 2] >= half_w + cfg.clearance_m / 2) & (c[:, 2] + half_w + cfg.lift_m < shelf.height_m)

    down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), c.shape)
    if cfg.approach == "front-first":
        a_hat = np.where(front_ok[:, None], a_front, down)
    else:
        a_hat = np.where(top_ok[:, None] | ~front_ok[:, None], down, a_front)
    taper = np.clip((max_w - width) / max(s, 1e-9), 0.0, 1.0)
    quality = np.where(width_ok & (top_ok | front_ok), taper, 0.0)
    conf = np.clip((cloud.occupancy.astype(np.float64) - 0.5) / 0.4, 0.0, 1.0)
    e = cfg.evidence * conf
    return GraspHypotheses(
        contact=c, mu_a_hat=np.ascontiguousarray(a_hat, dtype=np.float64),
        kappa_a_hat=np.full(n, cfg.kappa_a_hat) * np.maximum(conf, 0.1),
        mu_b=b, kappa_b=1.0 + cfg.kappa_b * conf * side,
        alpha=1.0 + e * quality, beta=1.0 + e * (1.0 - quality), width=width,
    )
