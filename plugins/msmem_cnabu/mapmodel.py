"""``cnabu-map``: sigma_o by the whole-map network (``mapnet``): the previous belief over every voxel and
the view's ray masks in, the next belief over every voxel out, with bounded evidence."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from scipy import ndimage

from msmem_cnabu.classmap import mapped_classes, onto_slots
from msmem_cnabu.configs import CNABUMapConfig
from msmem_cnabu.features import grid_interior, wall_mask
from msmem_cnabu.weights import load_map_net, resolve_weights
from msmem_core.errors import UserError
from msmem_core.interfaces import Observation, ObservationModel
from msmem_core.map.belief import EvidentialMap
from msmem_core.world.scene import model_classes

SHIPPED = Path(__file__).resolve().parent / "weights" / "cnabu_map.pt"


class CNABUMapObservationModel(ObservationModel):
    """sigma_o over the whole map (module docstring; the network: ``msmem_cnabu.mapnet``)."""

    def __init__(self, config: CNABUMapConfig | None = None) -> None:
        from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel

        self.config = cfg = config or CNABUMapConfig()
        path = resolve_weights(cfg.weights) if cfg.weights is not None else SHIPPED
        self.net, self.meta = load_map_net(path)
        self.meta["weights"] = str(path)
        trained = model_classes(self.meta.get("classes"), self.net.config.num_classes)
        self.classes = trained
        self._index: NDArray[np.int64] | None = None
        if cfg.class_map is not None:
            self.classes, self._index = mapped_classes(cfg.class_map, trained)
        self.rays = AnalyticObservationModel(AnalyticObservationConfig(
            pixel_stride=cfg.pixel_stride, surface_offset_m=cfg.surface_offset_m, far_m=cfg.far_m))
        self._valid: dict[Any, torch.Tensor] = {}
        self._ray_classes = np.zeros(0, dtype=bool)
        """``known_classes: rays``: the classes a ray of the current episode has labelled."""
        self._state: tuple[EvidentialMap, tuple[NDArray[np.float32], ...]] | None = None
        """``restrict_state: false`` or ``unlabelled_objects: unknown``: the belief last returned and the
        network's own evidence behind it (alpha, beta, eta), the next input when that belief comes back."""
        self._labelled = np.zeros((0, 0, 0, 0), dtype=bool)
        """``unlabelled_objects: unknown``: [C, X, Y, Z] where a ray of the current episode labelled class c."""
        self._rays: EvidentialMap | None = None
        """``observed_voxels: rays``: the analytic update's record of the current episode's rays (in the
        belief's class slots), cleared where an effect model's prediction rewrote the belief."""

    def valid(self, belief: EvidentialMap) -> torch.Tensor:
        g = belief.grid
        if g not in self._valid:
            net_shape = tuple(self.net.config.grid_shape)
            classes = self.net.config.num_classes if self._index is None else len(self._index)
            if tuple(g.shape) != net_shape or belief.num_classes != classes:
                raise UserError(f"cnabu-map: the weights were trained on a {net_shape} grid with "
                                f"{classes} classes{' (mapped)' if self._index is not None else ''}, the belief "
                                f"has {tuple(g.shape)} and {belief.num_classes}; train weights for this grid "
                                "(`msmem train cnabu-map`)")
            walls = wall_mask(g, grid_interior(g, self.config.margin_voxels))
            self._valid = {g: torch.from_numpy(~walls)}
        return self._valid[g]

    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap:
        return self.update_masks(belief, *self.rays.masks(belief, observation))

    def disturbed(self, region: NDArray[np.bool_], cap: float) -> None:
        """With ``disturbed_rays: cap``, the episode's ray record is capped in ``region`` as MSAS capped
        the belief: rays from before a manipulation count there as at most ``cap`` in all, so that the
        next views can overturn them (uncapped, the record's confident evidence is authoritative again
        at the next update). ``keep``, the default, leaves the record."""
        if self.config.disturbed_rays == "cap":
            self._cap_rays(region, cap)

    def failed_manipulation(self, region: NDArray[np.bool_], cap: float) -> None:
        """With ``disturbed_rays: cap`` or ``failed``, the ray record is capped in ``region`` after a
        manipulation that reported failure: what it touched may have moved somewhere the prediction does
        not say, so the rays from before must not restore it."""
        if self.config.disturbed_rays in ("cap", "failed"):
            self._cap_rays(region, cap)

    def _cap_rays(self, region: NDArray[np.bool_], cap: float) -> None:
        if self._rays is not None and self._rays.alpha.shape == region.shape:
            self._rays = self._rays.capped(region, cap)

    def _carried(self, belief: EvidentialMap, alpha: NDArray[np.float32], beta: NDArray[np.float32],
                 eta: NDArray[np.float32]) -> tuple[NDArray[np.float32], ...]:
        """A belief this model did not return, within an episode (an effect model's prediction made from the
        belief it last returned, perhaps with MSAS's evidence cap): the network's own map where every
        value is still the returned belief's, the given belief where something changed it."""
        prev, (sa, sb, se) = self._state  # type: ignore[misc]
        if prev.alpha.shape != belief.alpha.shape or prev.eta.shape != belief.eta.shape:
            return alpha, beta, eta
        same = (prev.alpha == belief.alpha) & (prev.beta == belief.beta) & (prev.eta == belief.eta).all(axis=0)
        if not same.any():
            return alpha, beta, eta
        return (np.where(same, sa, alpha).astype(np.float32), np.where(same, sb, beta).astype(np.float32),
                np.where(same[None], se, eta).astype(np.float32))

    @torch.no_grad()
    def update_masks(self, belief: EvidentialMap, free: NDArray[np.bool_], occ: NDArray[np.bool_],
                     seen: NDArray[np.bool_]) -> EvidentialMap:
        """The update from a view's ray masks (free, occ [X, Y, Z], seen [C, X, Y, Z])."""
        valid = self.valid(belief)
        alpha, beta, eta = belief.alpha, belief.beta, belief.eta
        own = self._state is not None and self._state[0] is belief
        if own:  # the unrestricted map behind the belief this model returned (in the trained slots)
            alpha, beta, eta = self._state[1]  # type: ignore[index]
        labels = seen  # in the belief's class slots
        if self._index is not None:  # the scene's classes into the trained ones (no evidence on the others)
            k = self.net.config.num_classes
            eta = eta if own else onto_slots(eta, self._index, k, fill=1)
            seen = onto_slots(seen, self._index, k, fill=False)
        if not own and self._state is not None and belief.observed is not None and belief.observed.any():
            alpha, beta, eta = self._carried(belief, alpha, beta, eta)
        old = torch.get_num_threads()
        if self.config.threads is not None:
            torch.set_num_threads(self.config.threads)
        known = None
        if self.config.known_classes == "rays":  # every class a ray of this episode labelled
            fresh = belief.observed is None or not belief.observed.any()  # an episode's first view
            if fresh or self._ray_classes.shape != (seen.shape[0],):
                self._ray_classes = np.zeros(seen.shape[0], dtype=bool)
            self._ray_classes |= seen.reshape(seen.shape[0], -1).any(axis=1)
            self._ray_classes[0] = False
            known = torch.from_numpy(self._ray_classes.copy())[None]
        try:
            t = torch.from_numpy
            args = (t(alpha)[None], t(beta)[None], t(eta)[None], t(free)[None], t(occ)[None], t(seen)[None],
                    valid, self.config.unseen_class_weight, known)
            drop = self.config.unlabelled_objects == "unknown"
            keep = drop or (not self.config.restrict_state and self.config.unseen_class_weight < 1.0)
            raw, (a, b, e) = self.net.step_both(*args) if keep else (None, self.net.step(*args))
        finally:
            torch.set_num_threads(old)
        ray = free | occ | seen.any(axis=0)
        observed = ray if belief.observed is None else belief.observed | ray
        out_eta = e[0].numpy() if self._index is None else np.ascontiguousarray(e[0].numpy()[self._index])
        out_a, out_b = a[0].numpy(), b[0].numpy()
        rays = self._ray_record(belief, free, occ, labels) if self.config.observed_voxels == "rays" else None
        if drop:
            if rays is not None:  # labelled: the class most of the episode's rays gave a voxel
                self._labelled = majority_labels(rays)
            else:  # labelled: any class a ray of the episode gave a voxel
                if belief.observed is None or not belief.observed.any() or self._labelled.shape != labels.shape:
                    self._labelled = np.zeros(labels.shape, dtype=bool)  # an episode's first view
                self._labelled |= labels
            if self.config.restrict_state and self.config.unseen_class_weight < 1.0:
                raw = (a, b, e)  # the restricted map is the next input, the objects' abstention is not
            unknown = unlabelled_objects(out_a / (out_a + out_b) > 0.5, out_eta, self._labelled, valid.numpy())
            out_a, out_b = out_a.copy(), out_b.copy()
            if self.config.unknown_evidence == "prior":  # p = 0.5 (a tie is free), no class evidence
                out_a[unknown] = out_b[unknown] = 1.0
                out_eta = out_eta.copy()
                out_eta[:, unknown] = 1.0
            else:
                out_a[unknown] = out_b[unknown] = (out_a[unknown] + out_b[unknown]) / 2  # p = 0.5: a tie is free
        if rays is not None:
            cfg, inside, mapped = self.config, valid.numpy(), self._index is not None
            net_eta = out_eta
            out_a, out_b, out_eta = fuse_rays(out_a, out_b, out_eta, rays, cfg.ray_confidence)
            if cfg.ray_ties == "network":
                break_ray_ties(out_eta, rays.eta, net_eta)
            unreached = inside & (rays.alpha == 1.0) & (rays.beta == 1.0)  # the record's occupancy is the prior
            named = rays.eta[1:].sum(axis=0) > rays.num_classes - 1  # a ray gave it an object class
            if cfg.unlabelled_columns == "unknown" or (cfg.unlabelled_columns == "auto" and mapped):
                unlabelled_columns(out_a, out_b, out_eta, unreached & ~named.any(axis=2)[:, :, None])
            if cfg.unreached_occupied == "least" or (cfg.unreached_occupied == "auto" and mapped):
                least_evidence(out_a, out_b, unreached)
            if cfg.ray_classes_within is not None:
                ray_classes_nearby((out_a / (out_a + out_b) > 0.5) & inside & ~named, out_eta,
                                   self._labelled if drop else majority_labels(rays), cfg.ray_classes_within)
            if cfg.fill_under_surfaces is not None:
                fill_under_surfaces(out_a, out_b, out_eta, observed, inside, cfg.fill_under_surfaces)
        out = EvidentialMap(belief.grid, out_a, out_b, out_eta, observed)
        if raw is not None:
            self._state = (out, tuple(x[0].numpy() for x in raw))  # the trained slots: the next input as is
        return out

    def _ray_record(self, belief: EvidentialMap, free: NDArray[np.bool_], occ: NDArray[np.bool_],
                    seen: NDArray[np.bool_]) -> EvidentialMap:
        """The episode's ray record after this view (``seen`` in the belief's class slots). It starts
        empty with an episode (a belief without an ``observed`` record); where the belief's record is
        cleared (``BeliefDelta.apply``: an effect model's prediction wrote there), it is the prior again."""
        r = self._rays
        if (belief.observed is None or not belief.observed.any() or r is None or r.grid != belief.grid
                or r.num_classes != belief.num_classes):
            r = EvidentialMap.empty(belief.grid, belief.num_classes)
        else:
            stale = ~belief.observed
            r.alpha[stale] = r.beta[stale] = 1.0
            r.eta[:, stale] = 1.0
        self._rays = self.rays.apply_masks(r, free, occ, seen)
        return self._rays


def majority_labels(rays: EvidentialMap) -> NDArray[np.bool_]:
    """[C, X, Y, Z]: voxel v is labelled with object class c where c is the ray record's most supported
    class there and some ray gave it (a view's segmentation noise alone does not label an object)."""
    top = np.argmax(rays.eta, axis=0)
    out = np.zeros(rays.eta.shape, dtype=bool)
    np.put_along_axis(out, top[None], (np.take_along_axis(rays.eta, top[None], axis=0) > 1.0), axis=0)
    out[0] = False
    return out


def fuse_rays(alpha: NDArray[np.float32], beta: NDArray[np.float32], eta: NDArray[np.float32], rays: EvidentialMap,
              confidence: float) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """The network's evidence with the ray record's where it is authoritative: the class evidence of
    every voxel a ray labelled (any class evidence above the prior, background on voxels seen free), the
    occupancy evidence where the record's expected occupancy is above ``confidence`` or below
    ``1 - confidence``. New arrays; the inputs are unchanged."""
    labelled = rays.eta.sum(axis=0) > rays.num_classes
    p = rays.expected_occupancy()
    sure = (p > confidence) | (p < 1.0 - confidence)
    return (np.where(sure, rays.alpha, alpha).astype(np.float32), np.where(sure, rays.beta, beta).astype(np.float32),
            np.where(labelled[None], rays.eta, eta).astype(np.float32))


RAY_TIE_EPSILON = 1e-3
"""The network's share in a tie of the ray record's classes (``ray_ties: network``)."""


def break_ray_ties(eta: NDArray[np.float32], ray_eta: NDArray[np.float32], net_eta: NDArray[np.floating],
                   epsilon: float = RAY_TIE_EPSILON) -> None:
    """In place: where the ray record's strongest object classes tie (at least one ray gave them), add
    ``epsilon`` times the network's object-class probabilities (``net_eta`` normalised over the object
    classes) to the tied classes of ``eta``, so that the network's class decides among them."""
    obj = ray_eta[1:]
    top = obj.max(axis=0)
    tied_classes = np.isclose(obj, top[None], rtol=1e-6, atol=0.0)
    tied = (tied_classes.sum(axis=0) > 1) & (top > 1.0)
    if not tied.any():
        return
    net = np.asarray(net_eta[1:, tied], dtype=np.float64)
    share = net / net.sum(axis=0, keepdims=True)
    eta[1:, tied] += (epsilon * share * tied_classes[:, tied]).astype(eta.dtype)


def unlabelled_columns(alpha: NDArray[np.float32], beta: NDArray[np.float32], eta: NDArray[np.float32],
                       where: NDArray[np.bool_]) -> None:
    """In place: the voxels of ``where`` (never reached by a ray, in a column in which no ray gave any
    voxel an object class) that are believed occupied go back to the prior (expected occupancy 0.5, no
    class evidence)."""
    m = (alpha / (alpha + beta) > 0.5) & where
    alpha[m] = beta[m] = 1.0
    eta[:, m] = 1.0


LEAST_OCCUPIED_ALPHA = 1.2
"""``unreached_occupied: least``: alpha of a never-reached voxel believed occupied (beta 1: p = 0.545)."""


def least_evidence(alpha: NDArray[np.float32], beta: NDArray[np.float32], unreached: NDArray[np.bool_]) -> None:
    """In place: the voxels of ``unreached`` (whose occupancy no ray gave) believed occupied keep the least
    evidence that calls them occupied (``LEAST_OCCUPIED_ALPHA``, 1)."""
    m = (alpha / (alpha + beta) > 0.5) & unreached
    alpha[m] = LEAST_OCCUPIED_ALPHA
    beta[m] = 1.0


def ray_classes_nearby(target: NDArray[np.bool_], eta: NDArray[np.float32], labelled: NDArray[np.bool_],
                       within: int) -> None:
    """In place: each ``target`` voxel (believed occupied, no ray gave it an object class) takes the
    object class of the nearest voxel that ``labelled`` [C, X, Y, Z] gives one (ties: any of them), if
    that is at most ``within`` voxels away: its object-class evidence above the prior (at least one)
    moves onto that class; its background evidence (a ray's, where one saw it) stays."""
    source = labelled[1:].any(axis=0)
    if not source.any() or not target.any():
        return
    dist, (ix, iy, iz) = ndimage.distance_transform_edt(~source, return_indices=True)
    m = target & ~source & (dist <= within)
    if not m.any():
        return
    xs, ys, zs = np.nonzero(m)
    near = np.argmax(labelled[1:, ix[m], iy[m], iz[m]], axis=0) + 1
    mass = np.maximum((eta[1:, xs, ys, zs] - 1.0).clip(min=0.0).sum(axis=0), 1.0)
    eta[1:, xs, ys, zs] = 1.0
    eta[near, xs, ys, zs] = 1.0 + mass


def fill_under_surfaces(alpha: NDArray[np.float32], beta: NDArray[np.float32], eta: NDArray[np.float32],
                        observed: NDArray[np.bool_], inside: NDArray[np.bool_], evidence: float) -> None:
    """In place: the voxels no ray reached (``~observed``) below the highest believed-occupied voxel of
    their column (within ``inside``) that are believed free become occupied with ``evidence`` and the
    top voxel's object class (as ``column-fill``)."""
    occ = (alpha / (alpha + beta) > 0.5) & inside
    z = occ.shape[2]
    top = z - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    below = (np.arange(z)[None, None, :] < top[:, :, None]) & occ.any(axis=2)[:, :, None]
    m = below & ~observed & inside & ~occ
    if not m.any():
        return
    top_cls = np.take_along_axis(np.argmax(eta[1:], axis=0) + 1, top[:, :, None], axis=2)[:, :, 0]
    xs, ys, zs = np.nonzero(m)
    f = np.float32(1 + evidence)
    alpha[m], beta[m] = f, 1.0
    eta[:, xs, ys, zs] = 1.0
    eta[top_cls[xs, ys], xs, ys, zs] = f


def unlabelled_objects(occupied: NDArray[np.bool_], eta: NDArray[np.floating], labelled: NDArray[np.bool_],
                       valid: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """[X, Y, Z] voxels of the objects no ray has labelled: the 26-connected components of the ``valid``
    voxels believed ``occupied`` whose top object class (of ``eta`` [C, X, Y, Z]) is one class c, for which
    no voxel of the component is ``labelled`` [C, X, Y, Z] with c."""
    top = np.argmax(eta[1:], axis=0) + 1
    hard = np.where(occupied & valid, top, 0)
    out = np.zeros(hard.shape, dtype=bool)
    for c in np.unique(hard[hard > 0]).tolist():
        lab, _ = ndimage.label(hard == c, structure=np.ones((3, 3, 3), dtype=bool))
        good = np.unique(lab[labelled[c] & (lab > 0)])
        out |= (lab > 0) & ~np.isin(lab, good)
    return out
