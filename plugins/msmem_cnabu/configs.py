"""Config models of the learned belief models (no torch import: the plugin registers them cheaply)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class CNABUObserveConfig(BaseModel):
    """Parameters of the learned observation update."""

    model_config = ConfigDict(extra="forbid")

    weights: Path | None = None
    """Weights file (None: the shipped ``msmem_cnabu/weights/cnabu_observe.pt``)."""
    margin_voxels: int = Field(1, ge=1, le=10)
    """The grid's margin around the shelf interior (``grid.margin_voxels``): the boards are never changed."""
    pixel_stride: int = Field(2, gt=0)
    """Ray masks from every n-th pixel (as ``analytic-observation``)."""
    surface_offset_m: float = Field(0.001, ge=0.0)
    """Depth returns are moved this far into the surface (as ``analytic-observation``)."""
    far_m: float = Field(1.5, gt=0.0)
    """Pixels without a return mark free space up to this z-depth."""
    threads: int | None = Field(None, ge=1)
    """torch threads while predicting (None: leave the process's setting)."""
    class_map: dict[str, str] | None = None
    """As ``cnabu-push``'s ``class_map``: each object class of the scene, in its order, to a distinct class
    the weights know (the rays' class labels go to the mapped classes). None: the trained classes."""


class CNABUEffectConfig(BaseModel):
    """Parameters of a learned effect model."""

    model_config = ConfigDict(extra="forbid")

    weights: Path | None = None
    """Weights file (None: the shipped ``msmem_cnabu/weights/cnabu_<kind>.pt``; a relative
    ``msmem_cnabu/weights/NAME`` names another shipped file, e.g. ``cnabu_push_map.pt``)."""
    change_threshold: float = Field(0.85, gt=0.0, lt=1.0)
    """A voxel changes where the predicted change probability exceeds this; elsewhere the prior is copied."""
    change_epsilon: float = Field(0.0, ge=0.0, lt=1.0)
    """Of those voxels, keep only the ones whose expected occupancy or an expected class probability
    moves by more than this (0: every voxel whose evidence differs). With a low ``change_threshold``
    the prediction is nearly dense but stays sparse: only moves of at most epsilon are dropped
    (docs/explanation/cnabu.md, "The change threshold")."""
    batch: int = Field(80, ge=1, le=1000)
    """Candidates per forward pass (80: all of a push skill's samples in one; larger batches are
    faster per candidate and need more working memory: docs/explanation/cnabu.md)."""
    threads: int | None = Field(None, ge=1)
    """torch threads while predicting (None: leave the process's setting)."""
    grasped_region: Literal["free", "network"] = "free"
    """``cnabu-grasp``: what the grasped object's believed region (as ``grasp-analytic`` finds it)
    becomes. ``free``: believed free with ``free_evidence`` over the network's prediction (the object
    left with the gripper; as ``grasp-analytic``'s ``target: free``), so rays pass where it stood.
    ``network``: as the network predicts it (it empties only part of it). Not used by ``cnabu-push``."""
    free_evidence: float = Field(20.0, ge=0.0)
    """``grasped_region: free``: its free and background-class evidence (two views' worth)."""
    class_map: dict[str, str] | None = None
    """For scenes whose classes the weights were not trained on: each object class of the scene, in the
    scene's order, to a distinct class the weights know, as ``cnabu-map``'s ``class_map`` (a run
    config's top-level ``class_map`` gives one map to every learned model). The network sees and
    predicts the mapped classes; the evidence of trained classes no scene class maps to is dropped.
    None: the scene's classes must be the trained ones (docs/explanation/cnabu.md)."""


class CNABUMapConfig(BaseModel):
    """Parameters of the whole-map observation model (``cnabu-map``)."""

    model_config = ConfigDict(extra="forbid")

    weights: Path | None = None
    """Weights file (None: the shipped ``msmem_cnabu/weights/cnabu_map.pt``; a relative
    ``msmem_cnabu/weights/NAME`` names another shipped file, e.g. ``cnabu_map_mesh.pt``)."""
    margin_voxels: int = Field(1, ge=1, le=10)
    """The grid's margin around the shelf interior (``grid.margin_voxels``): the boards get no residual."""
    pixel_stride: int = Field(2, gt=0)
    """Ray masks from every n-th pixel (as ``analytic-observation``)."""
    surface_offset_m: float = Field(0.001, ge=0.0)
    """Depth returns are moved this far into the surface (as ``analytic-observation``)."""
    far_m: float = Field(1.5, gt=0.0)
    """Pixels without a return mark free space up to this z-depth."""
    threads: int | None = Field(None, ge=1)
    """torch threads while predicting (None: leave the process's setting)."""
    unseen_class_weight: float = Field(1.0, gt=0.0, le=1.0)
    """Object classes the map does not know are in the scene (no ray has shown them where the map
    believes them) are down-weighted by this everywhere; 1: off (``mapnet.restrict_classes``)."""
    known_classes: Literal["belief", "rays"] = "belief"
    """With ``unseen_class_weight`` < 1, which classes count as known to be in the scene: ``belief``, those
    the map names or a ray hits where it names them (``mapnet.known_object_classes``); ``rays``, those any
    ray of the episode has labelled (what the analytic update has class evidence for)."""
    restrict_state: bool = True
    """With ``unseen_class_weight`` < 1: whether the restricted belief is also the network's next input.
    False: the model keeps the network's unrestricted map as its own state, and only the belief it
    returns (what the planner and the metrics read) is restricted. An episode's first belief is taken as
    it is; an effect model's prediction (made from the belief last returned) is the next input where it
    changed that belief, the network's own map everywhere else."""
    unlabelled_objects: Literal["keep", "unknown"] = "unknown"
    """What the returned belief says of an object the network predicts but no ray has labelled with its
    class (a 26-connected component of voxels believed occupied with one top object class, none of
    them labelled with it by a ray of the episode): ``keep`` it as predicted, or return it as
    ``unknown`` (expected occupancy 0.5, a tie, which counts as free, ``unknown_evidence``; the
    default), so that a hidden object's guessed class does not enter the maps. With
    ``unknown`` the network's own map stays its next input, through a manipulation too where the effect
    model's prediction left the returned belief unchanged (as with ``restrict_state: false``;
    docs/explanation/map-prediction.md)."""
    unknown_evidence: Literal["prior", "tie"] = "prior"
    """``unlabelled_objects: unknown``: the evidence of such an object's voxels. ``prior``: the prior
    (occupancy 1/2, no class evidence): nothing is known of it, so IG with ``gain: expected-reduction``
    credits a view or a manipulation that would show it. ``tie``: occupancy 1/2 with the network's
    total evidence kept, and its class evidence: to IG a confident tie, worth almost nothing to see.
    The maps are the same either way (a tie counts as free)."""
    class_map: dict[str, str] | None = None
    """For scenes whose classes the weights were not trained on: each object class of the scene, in the
    scene's order, to a distinct class the weights know (e.g. ``{cereal: cracker_box, ...}``). The
    network then sees and predicts the mapped classes; the evidence of trained classes no scene class
    maps to is dropped. None: the scene's classes must be the trained ones (docs/explanation/map-prediction.md)."""
    observed_voxels: Literal["rays", "network"] = "rays"
    """What the returned belief says of a voxel a ray of the episode has reached. ``rays``: the ray
    evidence is authoritative there (the analytic update's record of the episode, kept beside the
    network): its class evidence wherever a ray labelled the voxel (background on voxels seen free),
    and its occupancy evidence wherever that is confident (``ray_confidence``); the network predicts
    only what no ray reached, and a voxel an effect model's prediction rewrote (a push or grasp moved
    what was there) is the network's again until a ray reaches it. ``network``: the network's
    prediction everywhere (docs/explanation/map-prediction.md)."""
    ray_confidence: float = Field(0.5, ge=0.5, lt=1.0)
    """With ``observed_voxels: rays``: the ray record's occupancy is used where its expected occupancy is
    above this or below 1 minus this (0.5: wherever the rays lean either way; 0.9 would leave voxels
    seen hit by some views and passed by others to the network, which calls too many of them free)."""
    unlabelled_columns: Literal["auto", "keep", "unknown"] = "auto"
    """With ``observed_voxels: rays``: what the returned belief says of the voxels the network predicts
    occupied (no ray reached them) in a column in which no ray gave any voxel an object class. ``keep``:
    the network's prediction. ``unknown``: the prior (expected occupancy 0.5, which counts as free, no
    class evidence), as for ``unlabelled_objects``. ``auto`` (the default): ``unknown`` when a
    ``class_map`` maps the scene's classes onto the trained ones, ``keep`` otherwise. The network learnt
    the shapes of its trained objects: where they are the scene's, it rightly completes hidden objects in
    columns the rays never labelled; a mapped class is another object under a trained one's name, whose
    shape it does not know, and there its guesses cost both map metrics (docs/explanation/map-prediction.md,
    "Mesh objects"). Set ``keep`` for weights trained on the mapped classes' own shapes."""
    unreached_occupied: Literal["auto", "keep", "least"] = "auto"
    """With ``observed_voxels: rays``: the occupancy evidence of a voxel no ray reached that the network
    believes occupied. ``keep``: the network's. ``least``: the least that still calls it occupied
    (alpha 1.2, beta 1: expected occupancy 0.545), so the maps are the same but IG credits a view that
    would reach it almost as much as never-seen space. ``auto`` (the default): ``least`` when a
    ``class_map`` maps the scene's classes onto the trained ones (the network completes shapes it was
    not trained on), ``keep`` otherwise (docs/explanation/map-prediction.md, "Mesh objects")."""
    ray_classes_within: int | None = Field(None, ge=1, le=64)
    """With ``observed_voxels: rays``: a voxel believed occupied that no ray gave an object class takes
    its object class from the nearest voxel whose rays did (their majority class), if that is at most
    this many voxels away (Euclidean): the voxel's object-class evidence (at least one) moves onto that
    class; its background evidence and its occupancy stay. The network completes the hidden back and
    underside of an object whose faces the rays labelled, and the rays know that object's class better
    than the network's guess from its shape; an occupied voxel that rays labelled only background (an
    object's surface seen at a grazing angle) gets its object class the same way. None (the default):
    the network's class. Measured at 4 on ``tune10``, view-only, 40 steps: -0.012 +- 0.024 2-D semantic
    mIoU (per scene, paired), though +0.013 offline on ``hard25`` scenes 0-4 (docs/explanation/map-prediction.md)."""
    ray_ties: Literal["lowest", "network"] = "lowest"
    """With ``observed_voxels: rays``: where the rays gave a voxel two or more object classes equally
    often (its ray record's strongest object classes tie), ``network`` adds 0.001 times the network's
    object-class probabilities to those tied classes' evidence, so the network's class decides among
    them and nothing else changes; ``lowest`` (the default) leaves the tie, which the argmax decodes as
    the lowest class index. Measured on ``tune10``, 40 steps, per scene, paired: view-only +0.001 2-D
    semantic mIoU, grasp-only -0.011 +- 0.031 and ``ours`` -0.012 +- 0.031 (other grasps are taken);
    study: docs/lab/2026-12-05-stray-classes."""
    disturbed_rays: Literal["keep", "cap", "failed"] = "keep"
    """With ``observed_voxels: rays``: what a manipulation's disturbed region
    (``ObservationModel.disturbed``, where MSAS capped the belief's evidence) does to the episode's ray
    record. ``keep`` (the default) leaves it, so where the record is confident the next update restores
    the evidence from before the manipulation; ``cap`` caps it as MSAS capped the belief, and one view
    that sees such a voxel free overturns it; ``failed`` caps it only after a manipulation that reported
    failure (``ObservationModel.failed_manipulation``), where the object may have moved somewhere the
    prediction does not say. ``cap`` was measured on ``tune10`` and not adopted: in closed loop, 40
    steps, paired per scene, grasp-only +0.025 +- 0.071, ``ours`` +0.000 +- 0.066 and push-only -0.010
    +- 0.022 2-D semantic mIoU; executed from one state at step 10, the best grasp ended 0.042 lower and
    the best push 0.004 lower. Study: docs/lab/2026-12-05-decision-oracle (section 7). ``failed``,
    measured and not yet adopted: on ``tune10`` it changes 1 episode of 10 per method (+0.020 2-D
    semantic mIoU); on ``hard25`` 14 episodes move both ways, pooled +0.001 to +0.007
    (docs/lab/2026-12-06-failed-manipulation-rays)."""
    fill_under_surfaces: float | None = Field(2.0, gt=0.0, lt=10.0)
    """With ``observed_voxels: rays``: voxels no ray reached below a column's highest believed-occupied
    voxel that the network believes free are filled as ``column-fill`` fills them (occupied with this
    evidence, p = (1 + f) / (2 + f), and the top voxel's class): objects stand on the board. None: off."""
