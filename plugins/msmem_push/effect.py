"""Analytic push effect model (sigma_p, belief model ``push-analytic``, role *effect*).

What it predicts for a push (tool tip at ``height_m`` from ``start_m`` along ``direction`` for
``length_m``), from the belief alone:

- *Objects* are the connected components (26-neighbourhood) of believed-occupied voxels
  (p > ``occupied_threshold``) inside the shelf interior that share their argmax class, cut to the
  voxels within ``max_object_radius_m`` (horizontally) of where they are touched: touching objects
  of one class form one component, and the cut keeps a push from moving a whole row of them.
  Voxels believed occupied whose argmax class is background (shelf boards the observation update
  placed in the boundary layer of the interior) are structure, not objects: they never move.
- *Contact* is found per lane: the voxels of a pusher (first the tool at its start, rasterised;
  then each moved object) are binned by z layer and by their coordinate across the push; in each
  lane the nearest object voxel ahead of the pusher's leading voxel is what the pusher meets there.
  An object first in some lane is pushed by ``pusher travel - gap``, the gap being the free
  distance in front of the pusher (for the tool: from the exact leading face of the tool part at
  the contact's height). Objects behind another one in every lane are reached through the chain.
- *Chain*: up to ``max_chain`` links deep; an object counts as in a moved object's way only if it
  lies ahead of the moved object's overall leading voxel, not beside it (a neighbour in a row
  pushed at an angle slides along it). Moved objects stop at the side and back walls, and a jam
  propagates back (a pusher moves at most its gap plus what the object it pushes moves): the
  prediction is the rigid limit; in reality something would turn or topple.
- *Evidence*: a moved object's evidence moves with it (shifted by the displacement rounded to whole
  voxels, scaled towards the prior by ``moved_keep``); the voxels it left return to the prior
  (``vacated_keep``, default 0: nothing is known about what is behind); in the tool's swept volume
  and the region the moved objects swept (which includes the contacts) the *semantic* evidence
  loses confidence (Dirichlet evidence above the prior scaled by ``swept_keep``), so Delta-H and
  CDC see the disturbance. Their occupancy evidence is kept: space the tool or an object passed
  through is still free afterwards, and lowering it would only create information gain the push
  does not produce (a free voxel seen twice, p = 1/22, would leave IG's free clamp at p < 0.05).
- Not modelled: rotation of pushed objects, toppling, sliding after the tool stops, and the unseen
  parts of an object (only its believed-occupied voxels move; its unknown interior stays unknown
  where it was).

The prediction is sparse (a ``Prediction``: one ``BeliefDelta`` of the changed voxels per action). The
shelf interior and the tool's shape (the run's gripper, the action's ``palm``) come from the
``Workspace``. Work per action is a constant number of array operations on the voxels involved (no Python
loop over voxels); the components are labelled once per call.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import Action, EffectModel, Prediction, Workspace
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_push.geometry import Box, across, box6, swept_voxels
from msmem_push.skill import PushAction


class PushEffectConfig(BaseModel):
    """Parameters of the analytic push effect model."""

    model_config = ConfigDict(extra="forbid")

    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Voxels with expected occupancy above this belong to objects (and move with them)."""
    swept_keep: float = Field(0.5, ge=0.0, le=1.0)
    """Fraction of semantic evidence above the prior kept where the tool and the moved objects passed."""
    vacated_keep: float = Field(0.0, ge=0.0, le=1.0)
    """Fraction of evidence above the prior kept in voxels a moved object left (0: back to the prior)."""
    moved_keep: float = Field(1.0, ge=0.0, le=1.0)
    """Fraction of evidence above the prior a moved object carries to its predicted place."""
    max_chain: int = Field(3, ge=0, le=20)
    """How many objects deep a push propagates (tool -> object -> object ...)."""
    max_object_radius_m: float = Field(0.10, gt=0.0, le=1.0)
    """A moved object is its component's voxels within this horizontal distance of the contact
    (touching objects of one class form one component; the largest catalogue footprint, the
    cracker box, is 16 cm long)."""


@dataclass
class _Scene:
    """What every action's prediction reads from the belief, computed once per ``predict`` call."""

    labels: NDArray[np.int32]
    """[N] object instance per voxel (0: none)."""
    members: list[NDArray[np.int64]]
    """Flat voxel indices of each instance (index = label)."""
    centers: NDArray[np.float64]
    """[N, 3] voxel centres."""


class AnalyticPushEffect(EffectModel):
    def __init__(self, config: PushEffectConfig | None = None) -> None:
        self.config = config or PushEffectConfig()

    def _scene(self, belief: EvidentialMap, interior: tuple[float, ...]) -> _Scene:
        from scipy import ndimage
        grid = belief.grid
        c = grid.centers()
        lo, hi = np.asarray(interior[:3]), np.asarray(interior[3:])
        inside = np.all((c > lo) & (c < hi), axis=-1)
        cls = np.argmax(belief.eta, axis=0)
        occ = (belief.expected_occupancy() > self.config.occupied_threshold) & inside & (cls != 0)
        labels = np.zeros(grid.shape, np.int32)
        n = 0
        for k in np.unique(cls[occ]):
            lab, m = ndimage.label(occ & (cls == k), structure=np.ones((3, 3, 3), dtype=bool))
            labels[lab > 0] = lab[lab > 0] + n
            n += m
        flat = labels.ravel()
        order = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[order], np.arange(n + 2))
        members = [order[bounds[i] : bounds[i + 1]] for i in range(n + 1)]
        return _Scene(flat, members, c.reshape(-1, 3))

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        pushes = [a for a in actions if isinstance(a, PushAction)]
        if len(pushes) < len(actions):
            other = next(a for a in actions if not isinstance(a, PushAction))
            raise TypeError(f"push-analytic predicts push actions, got a {other.kind!r} action")
        if not pushes:
            return Prediction(belief, [])
        interior = workspace.interior_box
        scene = self._scene(belief, interior)
        mark = np.zeros(belief.grid.size, dtype=bool)
        changes = [self._predict_one(belief, scene, a, interior, a.tool(workspace.gripper), mark).against(belief)
                   for a in pushes]
        return Prediction(belief, changes)

    # ------------------------------------------------------------------------------------ one push
    def displacements(self, belief: EvidentialMap, action: PushAction, workspace: Workspace
                      ) -> list[tuple[NDArray[np.int64], float]]:
        """The bodies a push moves: (flat voxel indices, displacement in metres along the push)."""
        interior = workspace.interior_box
        scene = self._scene(belief, interior)
        return self._moves(belief.grid, scene, action, interior, action.tool(workspace.gripper))[0]

    def _body(self, scene: _Scene, label: int, contact: int, free: NDArray[np.bool_]) -> NDArray[np.int64]:
        """The voxels of instance ``label`` within ``max_object_radius_m`` (xy) of the contact voxel
        that no other moved body claimed."""
        vox = scene.members[label]
        dxy = scene.centers[vox, :2] - scene.centers[contact, :2]
        keep = (np.einsum("ij,ij->i", dxy, dxy) <= self.config.max_object_radius_m**2) & free[vox]
        return vox[keep]

    @staticmethod
    def _first_contacts(labels: NDArray[np.int32], vox: NDArray[np.int64], gap: NDArray[np.float64]
                        ) -> dict[int, tuple[float, int]]:
        """Per instance among ``vox`` (labels > 0): the smallest gap and the voxel that has it."""
        order = np.lexsort((gap, labels))
        lab = labels[order]
        first = np.ones(len(lab), dtype=bool)
        first[1:] = lab[1:] != lab[:-1]
        return {int(lab[i]): (float(gap[order[i]]), int(vox[order[i]])) for i in np.flatnonzero(first)}

    def _moves(self, grid: Any, scene: _Scene, a: PushAction, interior: tuple[float, ...], tool: Sequence[Box]
               ) -> tuple[list[tuple[NDArray[np.int64], float]], NDArray[np.int64]]:
        s = grid.voxel_m
        u = np.asarray(a.direction, dtype=np.float64)
        start = np.asarray(a.start_m, dtype=np.float64)
        length = float(a.length_m)
        # the tool is the first pusher: its voxels at the start, moving by the push length
        tool_vox = swept_voxels(grid, start, u, a.height_m, tool, length * u)
        free = np.ones(grid.size, dtype=bool)
        at_start = swept_voxels(grid, start, u, a.height_m, tool)
        entered = 0.0
        while len(at_start) == 0 and entered < length:  # a tool starting in front of the grid: where it enters
            entered += s
            at_start = swept_voxels(grid, start + entered * u, u, a.height_m, tool)
        contacts = self._ahead(grid, scene, at_start, length, u, free, beside=True)
        # the gap to the tool from its exact leading face (the part at the contact's height)
        ext = 0.5 * grid.voxel_m * (abs(u[0]) + abs(u[1]))
        for lab, (_, v) in list(contacts.items()):
            z = scene.centers[v, 2] - a.height_m
            side = float((scene.centers[v, :2] - start) @ across(u))  # a part beside the contact's lane is not it
            half = max((b[4] + b[0] for b in map(box6, tool)
                        if b[2] - ext < z < b[3] + ext and abs(side - b[5]) < b[1] + s), default=0.0)
            contacts[lab] = (max(0.0, float((scene.centers[v, :2] - start) @ u) - half - ext), v)
        vox_of: list[NDArray[np.int64]] = []
        dist: list[float] = []
        links: list[tuple[int, int, float]] = []  # (pusher, pushed, gap) of the chain
        for lab, (g, v) in sorted(contacts.items(), key=lambda kv: kv[1][0]):
            if g >= length:
                continue
            body = self._body(scene, lab, v, free)
            if len(body) == 0:
                continue
            free[body] = False
            vox_of.append(body)
            dist.append(self._wall_clamp(scene, body, u, length - g, interior, s))
        frontier = list(range(len(vox_of)))
        for _ in range(self.config.max_chain):  # objects in the way of moved objects, breadth first
            nxt: list[int] = []
            for i in frontier:
                if dist[i] <= 0.0:
                    continue
                ahead = self._ahead(grid, scene, vox_of[i], dist[i], u, free)
                for lab, (g, v) in sorted(ahead.items(), key=lambda kv: kv[1][0]):
                    if g >= dist[i]:
                        continue
                    other = self._body(scene, lab, v, free)
                    if len(other) == 0:
                        continue
                    free[other] = False
                    links.append((i, len(vox_of), g))
                    nxt.append(len(vox_of))
                    vox_of.append(other)
                    dist.append(self._wall_clamp(scene, other, u, dist[i] - g, interior, s))
            if not nxt:
                break
            frontier = nxt
        # a jam propagates back: a pusher moves at most its gap plus what the object it pushes moves
        for i, j, g in reversed(links):
            dist[i] = min(dist[i], g + dist[j])
        return [(v, d) for v, d in zip(vox_of, dist, strict=True) if d > 0.0], tool_vox

    @staticmethod
    def _wall_clamp(
        scene: _Scene, body: NDArray[np.int64], u: NDArray[np.float64], d: float, interior: tuple[float, ...], s: float
    ) -> float:
        """The displacement after which the body's voxels would cross a side or the back wall."""
        c = scene.centers[body, :2]
        x_lo, _, _, x_hi, y_hi, _ = interior
        limit = d
        for axis, lo, hi in ((0, x_lo, x_hi), (1, None, y_hi)):
            if u[axis] > 1e-9:
                limit = min(limit, float((hi - c[:, axis].max() - s / 2) / u[axis]))
            elif u[axis] < -1e-9 and lo is not None:
                limit = min(limit, float((c[:, axis].min() - lo - s / 2) / -u[axis]))
        return max(0.0, limit)

    def _ahead(self, grid: Any, scene: _Scene, body: NDArray[np.int64], d: float, u: NDArray[np.float64],
               free: NDArray[np.bool_], beside: bool = False) -> dict[int, tuple[float, int]]:
        """What a body moving by d along u runs into: per lane (across the push, per z layer) the
        nearest unclaimed object voxel ahead of the body's leading voxel in that lane; per instance
        that is first in some lane, the smallest gap and the voxel it is measured at. Objects behind
        another one in every lane are reached through the chain, not directly. Unless ``beside``,
        voxels not ahead of the body's overall leading voxel are ignored (an object the body only
        grazes sideways, e.g. its neighbour in a row pushed at an angle, slides along it)."""
        s = grid.voxel_m
        if len(body) == 0:  # e.g. a tool starting wholly in front of the shelf: nothing to run into yet
            return {}
        ext = 0.5 * s * (abs(u[0]) + abs(u[1]))
        w = across(u)
        ca = scene.centers[body]
        travel = np.array([*(d * u), 0.0])
        lo = ca.min(axis=0) - s + np.minimum(0.0, travel)
        hi = ca.max(axis=0) + s + np.maximum(0.0, travel)
        ijk_lo = np.maximum(np.floor((lo - grid.origin) / s).astype(np.int64), 0)
        ijk_hi = np.minimum(np.floor((hi - grid.origin) / s).astype(np.int64), np.asarray(grid.shape) - 1)
        lab3 = scene.labels.reshape(grid.shape)
        free3 = free.reshape(grid.shape)
        sl = tuple(slice(a, b + 1) for a, b in zip(ijk_lo, ijk_hi, strict=True))
        rel = np.argwhere((lab3[sl] > 0) & free3[sl])
        if len(rel) == 0:
            return {}
        ijk = rel + ijk_lo
        flat = (ijk[:, 0] * grid.shape[1] + ijk[:, 1]) * grid.shape[2] + ijk[:, 2]
        cb = scene.centers[flat]
        # lanes: across-coordinate bin and z layer
        a_lane = np.floor(ca[:, :2] @ w / s + 0.5).astype(np.int64)
        b_lane = np.floor(cb[:, :2] @ w / s + 0.5).astype(np.int64)
        a_k = np.floor((ca[:, 2] - grid.origin[2]) / s).astype(np.int64)
        lane_lo = min(a_lane.min(), b_lane.min())
        width = max(a_lane.max(), b_lane.max()) - lane_lo + 1
        a_key = a_k * width + (a_lane - lane_lo)
        b_key = ijk[:, 2] * width + (b_lane - lane_lo)
        lead = np.full(int(max(a_key.max(), b_key.max())) + 1, -np.inf)
        np.maximum.at(lead, a_key, ca[:, :2] @ u)
        along_b = cb[:, :2] @ u
        ahead = along_b - lead[b_key]
        ok = np.isfinite(ahead) & (ahead > 0)
        if not beside:
            ok &= along_b > lead[np.isfinite(lead)].max()
        if not ok.any():
            return {}
        key, vox, gap = b_key[ok], flat[ok], np.maximum(0.0, ahead[ok] - 2 * ext)
        order = np.lexsort((gap, key))  # the nearest voxel of each lane
        first = np.ones(len(order), dtype=bool)
        first[1:] = key[order][1:] != key[order][:-1]
        pick = order[first]
        near = gap[pick] < d
        return self._first_contacts(scene.labels[vox[pick][near]], vox[pick][near], gap[pick][near])

    def _predict_one(self, belief: EvidentialMap, scene: _Scene, a: PushAction, interior: tuple[float, ...],
                     tool: Sequence[Box], mark: NDArray[np.bool_]) -> BeliefDelta:
        """One action's change (its voxels may include some whose evidence stays the same); ``mark``
        is an all-False scratch mask [N] (left all-False)."""
        cfg = self.config
        grid = belief.grid
        s = grid.voxel_m
        nx, ny, nz = grid.shape
        u = np.asarray(a.direction, dtype=np.float64)
        moved, tool_vox = self._moves(grid, scene, a, interior, tool)
        src_parts, dst_parts, dst_from, path_parts = [], [], [], [tool_vox]
        for vox, d in moved:
            shift = np.rint(d * u / s).astype(np.int64)
            if not shift.any():
                continue
            # the region the body sweeps: one copy per voxel of travel, the last one its new place
            steps = max(1, int(np.abs(shift).max()))
            st = np.rint(np.arange(1, steps + 1)[:, None] / steps * shift[None, :]).astype(np.int64)
            i, j = vox // (ny * nz), (vox // nz) % ny
            qi = i[None, :] + st[:, :1]
            qj = j[None, :] + st[:, 1:]
            ok = (qi >= 0) & (qi < nx) & (qj >= 0) & (qj < ny)
            fl = vox[None, :] + (qi - i[None, :]) * (ny * nz) + (qj - j[None, :]) * nz
            path_parts.append(fl[ok])
            dst_parts.append(fl[-1][ok[-1]])
            dst_from.append(vox[ok[-1]])
            src_parts.append(vox)
        empty = np.zeros(0, np.int64)
        path = np.concatenate(path_parts)  # a voxel swept by several copies of a body: keep it once
        mark[path] = True
        path = np.flatnonzero(mark)
        mark[path] = False
        src = np.concatenate(src_parts) if src_parts else empty
        dst = np.concatenate(dst_parts) if dst_parts else empty
        frm = np.concatenate(dst_from) if dst_from else empty
        for part in (path, src, dst):
            mark[part] = True
        idx = np.flatnonzero(mark)
        mark[idx] = False
        alpha = belief.alpha.reshape(-1)
        beta = belief.beta.reshape(-1)
        eta = belief.eta.reshape(belief.num_classes, -1)

        def toward_prior(x: NDArray[np.float32], keep: float) -> NDArray[np.float32]:
            return (1.0 + (x - 1.0) * np.float32(keep)).astype(np.float32)

        old = alpha[idx], beta[idx], eta[:, idx]
        na, nb, ne = (x.copy() for x in old)
        pos = np.searchsorted(idx, path)
        ne[:, pos] = toward_prior(eta[:, path], cfg.swept_keep)
        pos = np.searchsorted(idx, src)
        na[pos], nb[pos], ne[:, pos] = (toward_prior(v, cfg.vacated_keep) for v in (alpha[src], beta[src], eta[:, src]))
        pos = np.searchsorted(idx, dst)
        na[pos] = toward_prior(alpha[frm], cfg.moved_keep)
        nb[pos] = toward_prior(beta[frm], cfg.moved_keep)
        ne[:, pos] = toward_prior(eta[:, frm], cfg.moved_keep)
        return BeliefDelta(idx, na, nb, ne)
