"""Analytic grasp effect model (sigma_g, belief model ``grasp-analytic``, role *effect*).

What it predicts for a grasp (``GraspAction``: pose, width, lift and retreat out of the shelf
front), from the belief alone:

- *Objects* are the connected components (26-neighbourhood) of believed-occupied voxels
  (p > ``occupied_threshold``) of one argmax class inside the shelf interior
  (``planning.Objects``).
- *The grasped object* is its class's component at the contact clipped to the gripper's opening
  box (``Objects.region``: within the opening across the closing axis, ``max_object_radius_m``
  across it), so touching objects of the same class stay separate. Its voxels return to the prior
  (``target_keep`` of the evidence above the prior is kept; default 0): it leaves, and what is
  behind it is unknown until seen. The whole object (the region and its component's voxels above
  and beside it, ``removal``) is reported in ``Prediction.excluded`` so a CDC term does not count the
  intended removal as collateral damage.
- *The way out*: the object (its believed region plus the hidden voxels below it down to the floor
  that are not believed free, ``planning.fill_down``), lifted by the action's lift, is carried
  straight out of the shelf front (-y) with the closed gripper. Every other object whose believed
  voxels this corridor (the object swept along the lift and the retreat, plus the closed gripper's
  boxes swept the same way) meets is pushed ahead of it and, since the retreat ends beyond the
  opening, out of the shelf: in PyBullet an object in the way is pushed off the shelf's front edge
  (docs/explanation/grasp.md). A pushed object's own way out can meet further objects (a chain, ``max_chain``
  deep). A pushed object is its component's voxels within ``max_object_radius_m`` of where it is
  first met.
- *Evidence*: the voxels a pushed object left are believed free (``free_evidence`` of free and
  background-class evidence, the weight of two views, so they are confident): each confident voxel
  of a neighbour's class becomes confident background, which is what a CDC term counts (a reset to
  the prior would hide the damage from it: CDC counts only voxels confident afterwards). Nothing
  else in the corridor changes. Objects merely touching the grasped one stay (docs/explanation/grasp.md);
  ``touch_shift_m`` > 0 shifts them along the retreat instead.
- Not modelled: toppling, rotation, the grasp failing (the prediction is the successful grasp), and
  the unseen parts of other objects (only believed-occupied voxels move).

The prediction is sparse (a ``Prediction``: one ``BeliefDelta`` of the changed voxels per action, and
per action the grasped object as ``excluded``). The shelf interior and the gripper come from
the ``Workspace``. The components are labelled once per call.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import Action, EffectModel, Prediction, Workspace
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_grasp.planning import (
    Objects,
    fill_down,
    gripper_points,
    path_offsets,
    shift_voxels,
    swept_indices,
    under_top,
    way_out,
)
from msmem_grasp.skill import GraspAction

I64 = NDArray[np.int64]


REMOVAL_MARGIN_M = 0.02
"""Columns within this of a grasped region's belong to the removal (the skill's ``exit_margin_m``)."""


class GraspEffectConfig(BaseModel):
    """Parameters of the analytic grasp effect model (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Voxels with expected occupancy above this belong to objects."""
    max_object_radius_m: float = Field(0.10, gt=0.0, le=1.0)
    """An object (grasped or pushed) reaches at most this far across from where it is touched."""
    target: Literal["free", "prior"] = "free"
    """What the grasped object's region becomes. ``free``: believed free with ``free_evidence`` (the
    object left with the gripper, so rays pass where it stood and the view after the grasp is scored
    for what it reveals behind it; what is behind keeps its belief until seen). ``prior``: the prior
    (``target_keep`` of its evidence kept), as MEM; rays through a prior voxel go on with probability
    1/2 only, so a grasped box of six voxels depth still hides what is behind it from the prediction."""
    target_keep: float = Field(0.0, ge=0.0, le=1.0)
    """``target: prior``: fraction of evidence above the prior kept in the grasped object's region (0: the prior)."""
    free_evidence: float = Field(20.0, ge=0.0)
    """Free (Beta beta) and background-class evidence of the voxels a pushed-out object left
    (20 = two views of the analytic observation model: p = 1/22, vacuity 15/35 < tau_chi)."""
    free_threshold: float = Field(0.3, gt=0.0, lt=0.5)
    """Below a believed object, voxels down to the floor that are not believed free (p below this)
    are taken as its hidden lower part when it is carried out."""
    max_chain: int = Field(3, ge=0, le=20)
    """How many objects deep a push-out propagates (grasped object -> object -> object ...)."""
    tolerance_m: float = Field(0.003, ge=0.0, le=0.01)
    """The gripper's boxes are shrunk by this (as in the skill's collision test)."""
    touch_shift_m: float = Field(0.0, ge=0.0, le=0.2)
    """Objects touching the grasped one (and not in the way) are shifted this far along the retreat."""


def emptied(belief: EvidentialMap, delta: BeliefDelta, region: I64, evidence: float) -> BeliefDelta:
    """``delta`` with the voxels ``region`` (flat indices) believed free: Beta ``(1, 1 + evidence)``
    and background-class evidence ``1 + evidence`` (what a grasped object leaves, ``target: free``)."""
    region = np.asarray(region, dtype=np.int64)
    if not len(region):
        return delta
    idx = np.union1d(delta.idx, region)
    c = belief.num_classes
    a = belief.alpha.reshape(-1)[idx].copy()
    b = belief.beta.reshape(-1)[idx].copy()
    e = belief.eta.reshape(c, -1)[:, idx].copy()
    at = np.searchsorted(idx, delta.idx)
    a[at], b[at], e[:, at] = delta.alpha, delta.beta, delta.eta
    r = np.searchsorted(idx, region)
    f = np.float32(evidence)
    a[r], b[r], e[:, r] = 1.0, 1.0 + f, 1.0
    e[0, r] += f
    return BeliefDelta(idx, a.astype(np.float32), b.astype(np.float32), e.astype(np.float32))


class AnalyticGraspEffect(EffectModel):
    def __init__(self, config: GraspEffectConfig | None = None) -> None:
        self.config = config or GraspEffectConfig()

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        grasps = [a for a in actions if isinstance(a, GraspAction)]
        if len(grasps) < len(actions):
            other = next(a for a in actions if not isinstance(a, GraspAction))
            raise TypeError(f"grasp-analytic predicts grasp actions, got a {other.kind!r} action")
        if not grasps:
            return Prediction(belief, [], excluded=[])
        objects = Objects.of(belief, workspace.interior_box, self.config.occupied_threshold)
        changes, excluded = [], []
        occupied = self.occupied(belief)
        for a in grasps:
            d, _region = self._predict_one(belief, objects, a, workspace.gripper)
            changes.append(d.against(belief))
            excluded.append(self.removal(belief, objects, a, occupied))
        return Prediction(belief, changes, excluded=excluded)

    def removal(self, belief: EvidentialMap, objects: Objects, a: GraspAction,
                occupied: NDArray[np.bool_] | None = None) -> I64:
        """The grasp's intended removal, which a CDC term does not count as collateral damage: the
        whole grasped object, its region (``target_region``) and its component's voxels in the columns
        within ``REMOVAL_MARGIN_M`` of the region's, at any height (``Objects.carried``; the skill
        carries the same body out of the shelf), and the believed-occupied voxels below its top in its
        columns (``planning.under_top``: its own voxels that the belief gave another class). The region
        alone is clipped to the opening: a tall object's upper part, which leaves with it, counted as
        damage, and so did bands of the object labelled another class. ``occupied``: the flat mask of
        believed-occupied voxels, when the caller has it (one per belief, not per grasp)."""
        label, region = self.target_region(belief, objects, a)
        body = objects.carried(belief.grid, label, region, REMOVAL_MARGIN_M)
        if not len(body):
            return body
        if occupied is None:
            occupied = self.occupied(belief)
        return np.union1d(body, np.flatnonzero(occupied & under_top(belief.grid, body)))

    def occupied(self, belief: EvidentialMap) -> NDArray[np.bool_]:
        """Flat mask of the believed-occupied voxels (expected occupancy above ``occupied_threshold``)."""
        return belief.expected_occupancy().reshape(-1) > self.config.occupied_threshold

    # ----------------------------------------------------------------------------------- one grasp
    def target_region(self, belief: EvidentialMap, objects: Objects, a: GraspAction) -> tuple[int, I64]:
        """(component label, flat voxel indices) of the grasped object."""
        grid = belief.grid
        pose = a.matrix
        inner = np.asarray(a.contact_m) + 0.5 * grid.voxel_m * pose[:3, 0]
        cls = None if a.target_class is None else np.array([a.target_class])
        label = int(objects.label_at(grid, inner[None], cls)[0])
        if label <= 0:
            return 0, np.zeros(0, np.int64)
        return label, objects.region(grid, label, pose, a.opening_m, self.config.max_object_radius_m)

    def moves(self, belief: EvidentialMap, objects: Objects, a: GraspAction, gripper: GripperSpec
              ) -> tuple[I64, list[I64], I64, list[tuple[I64, int]]]:
        """(grasped region, bodies pushed out of the shelf, corridor swept on the way out, touching
        bodies shifted by whole voxels along -y) of one grasp with ``gripper``."""
        cfg = self.config
        grid = belief.grid
        s = grid.voxel_m
        label, region = self.target_region(belief, objects, a)
        labels = objects.labels.reshape(-1)
        taken = np.zeros(grid.size, dtype=bool)
        taken[region] = True
        lift = round(max(0.0, a.retreat_m[0][2] - a.pose[2][3]) / s) if a.retreat_m else 0
        # the grasped object's way out (its hidden lower part included) and the closed gripper's
        # sweep along the lift and the retreat
        p = belief.expected_occupancy()
        lab3 = objects.labels
        body_path, body_step = way_out(grid, fill_down(grid, p, lab3, region, label, cfg.free_threshold), lift)
        grasp = a.matrix[:3, 3]
        path = path_offsets(np.array([grasp, *a.retreat_m]), s / 2) if a.retreat_m else grasp[None]
        pts = gripper_points(gripper, a.width_m, s / 2, cfg.tolerance_m, a.hand_m)
        grip = swept_indices(grid, a.matrix[:3, :3], pts, path)
        grip_y = grasp[1] - np.unravel_index(grip, grid.shape)[1] * s  # how far the gripper has come when there
        grip_step = np.maximum(0, np.round(grip_y / s)).astype(np.int64) + lift
        corridor = [body_path, grip]
        frontier = [(np.concatenate([body_path, grip]), np.concatenate([body_step, grip_step]))]
        pushed: list[I64] = []
        for _ in range(cfg.max_chain + 1):
            nxt = []
            for sweep, step in frontier:
                hit = labels[sweep] > 0
                hit &= ~taken[sweep]
                if not hit.any():
                    continue
                hv, hs = sweep[hit], step[hit]
                order = np.lexsort((hs, labels[hv]))  # per object, the first voxel met
                hv, hs = hv[order], hs[order]
                first = np.r_[True, labels[hv][1:] != labels[hv][:-1]]
                for v in hv[first][np.argsort(hs[first], kind="stable")]:
                    body = self._body(grid, objects, int(labels[v]), int(v), taken)
                    if not len(body):
                        continue
                    taken[body] = True
                    pushed.append(body)
                    path_b, step_b = way_out(grid, fill_down(grid, p, lab3, body, int(labels[v]),
                                                              cfg.free_threshold), 0)
                    corridor.append(path_b)
                    nxt.append((path_b, step_b))
            if not nxt or len(pushed) > 64:
                break
            frontier = nxt
        touching: list[tuple[I64, int]] = []
        if cfg.touch_shift_m > 0 and len(region) and label > 0:
            near = np.zeros(grid.size, dtype=bool)
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    for dk in (-1, 0, 1):
                        f, ok = shift_voxels(grid, region, di, dj, dk)
                        near[f[ok]] = True
            others = np.unique(labels[near & (labels > 0) & ~taken])
            for lab in others:
                v = int(np.flatnonzero(near & (labels == lab))[0])
                body = self._body(grid, objects, int(lab), v, taken)
                if len(body):
                    taken[body] = True
                    touching.append((body, round(cfg.touch_shift_m / s)))
        return region, pushed, np.unique(np.concatenate(corridor)), touching

    def _body(self, grid: GridSpec, objects: Objects, label: int, contact: int, taken: NDArray[np.bool_]) -> I64:
        """Voxels of component ``label`` within ``max_object_radius_m`` (xy) of the contact voxel
        not already taken by another body."""
        vox = np.flatnonzero(objects.labels.reshape(-1) == label)
        vox = vox[~taken[vox]]
        ijk = np.stack(np.unravel_index(vox, grid.shape), -1)
        c = np.array(np.unravel_index(contact, grid.shape))
        d = np.hypot(*(ijk[:, :2] - c[:2]).T) * grid.voxel_m
        return vox[d <= self.config.max_object_radius_m]

    def _predict_one(self, belief: EvidentialMap, objects: Objects, a: GraspAction, gripper: GripperSpec
                     ) -> tuple[BeliefDelta, I64]:
        cfg = self.config
        grid = belief.grid
        region, pushed, _corridor, touching = self.moves(belief, objects, a, gripper)
        src = np.concatenate([region, *pushed]) if pushed else region
        moved_from, moved_to = [], []
        for body, m in touching:
            f, ok = shift_voxels(grid, body, 0, -m, 0)
            moved_from.append(body[ok])
            moved_to.append(f[ok])
        frm = np.concatenate(moved_from) if moved_from else np.zeros(0, np.int64)
        dst = np.concatenate(moved_to) if moved_to else np.zeros(0, np.int64)
        vacated = np.concatenate([b for b, _ in touching]) if touching else np.zeros(0, np.int64)
        gone = np.concatenate(pushed) if pushed else np.zeros(0, np.int64)
        idx = np.unique(np.concatenate([src, vacated, dst]))
        alpha = belief.alpha.reshape(-1)
        beta = belief.beta.reshape(-1)
        eta = belief.eta.reshape(belief.num_classes, -1)
        na, nb, ne = alpha[idx].copy(), beta[idx].copy(), eta[:, idx].copy()

        def at(v: I64) -> I64:
            return np.searchsorted(idx, v)

        def prior(p: I64, keep: float) -> None:
            na[p] = 1.0 + (na[p] - 1.0) * np.float32(keep)
            nb[p] = 1.0 + (nb[p] - 1.0) * np.float32(keep)
            ne[:, p] = 1.0 + (ne[:, p] - 1.0) * np.float32(keep)

        prior(at(vacated), 0.0)
        if cfg.target == "prior":
            prior(at(region), cfg.target_keep)
        else:
            gone = np.concatenate([region, gone])
        pg = at(gone)  # the grasped and the pushed objects left: their voxels are believed free (confidently)
        na[pg], nb[pg], ne[:, pg] = 1.0, 1.0 + np.float32(cfg.free_evidence), 1.0
        ne[0, pg] += np.float32(cfg.free_evidence)
        if len(dst):
            pd = at(dst)
            na[pd], nb[pd], ne[:, pd] = alpha[frm], beta[frm], eta[:, frm]
        return BeliefDelta(idx, na.astype(np.float32), nb.astype(np.float32), ne.astype(np.float32)), region

    def displacements(self, belief: EvidentialMap, action: GraspAction, workspace: Workspace) -> dict[str, Any]:
        """What one grasp does to the believed objects: the grasped region, the bodies pushed out,
        the corridor (flat voxel indices) — for tests and inspection."""
        objects = Objects.of(belief, workspace.interior_box, self.config.occupied_threshold)
        region, pushed, corridor, touching = self.moves(belief, objects, action, workspace.gripper)
        return {"region": region, "pushed": pushed, "corridor": corridor, "touching": touching}
