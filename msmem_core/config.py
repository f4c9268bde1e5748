"""Run configuration: pydantic models, YAML/JSON files and method presets.

Precedence: the ``--method`` preset < a ``--config`` file < CLI flags. Unknown keys and bad values
are rejected with the dotted path of the field at fault.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import BaseModel, Field, ValidationError, model_validator

from msmem_core.errors import UserError
from msmem_core.map.belief import check_grid_memory
from msmem_core.map.ig import IGConfig
from msmem_core.plugins.manager import ComponentRef
from msmem_core.util.validation import MODEL_CONFIG, Int, error_lines, load_json, load_yaml
from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.scene import ClassName, relative_mesh_files
from msmem_core.world.scenegen import SceneGenConfig
from msmem_core.world.viewpoints import ViewpointConfig

METHODS = ("view-only", "push-only", "grasp-only", "no-cdc", "ours")
DEFAULT_METHOD = "ours"


def library_defaults() -> dict[str, Any]:
    """The settings every run starts from (``msmem_core/presets/defaults.yaml``): a preset, a config file
    and flags go over them."""
    return load_yaml(resources.files("msmem_core.presets").joinpath("defaults.yaml").read_text()) or {}


class _Strict(BaseModel):
    model_config = MODEL_CONFIG


class GridConfig(_Strict):
    voxel_m: float = Field(0.01, gt=0.001, le=0.05)
    """Voxel edge; the grid covers the shelf interior plus ``margin_voxels`` on every side."""
    margin_voxels: Int = Field(1, ge=1, le=10)
    """Voxels of margin around the shelf interior (they hold the boards the cameras see)."""


class SceneConfig(_Strict):
    file: Path | None = None
    """A SceneSpec JSON file; when unset the generator builds one from ``seed``."""
    seed: Int = 0
    """Seed of the generated scene (ignored when ``file`` is set)."""
    generator: SceneGenConfig = SceneGenConfig()


class TermRef(ComponentRef):
    """An objective term and its weight in the weighted sum."""

    weight: float = 1.0
    """Weight of the term in the objective's sum."""


class SkillRef(ComponentRef):
    """A skill and (for manipulation skills) the belief model that predicts its effect."""

    effect_model: ComponentRef | None = None


FALL_TILT_DEG = 30.0
"""An object whose up axis a manipulation tilted more than this has fallen over."""


class MSASConfig(_Strict):
    tau_chi: float = Field(0.5, gt=0.0, le=1.0)
    """Semantic vacuity below which a voxel's class counts as known (paper: tau_chi)."""
    manipulation_window: tuple[Int, Int] = (3, 25)
    """Steps (inclusive) in which manipulation may be chosen: 3 to 25 leaves at least 14 views to check
    the last one's outcome ([MEM]: 3 to 38, ``examples/mem-rules.yaml``; docs/explanation/msas.md)."""
    conf_cutoff: float = Field(0.85, gt=0.0, lt=1.0)
    """A BEV cell counts as mapped when its max class probability (MEM's p^1.8 scaling) exceeds this."""
    mapped_fraction: float = Field(0.99, gt=0.0, le=1.0)
    """Manipulation is disabled once this fraction of BEV cells is mapped ([MEM])."""
    start_view: Int | None = Field(None, ge=0)
    """Viewpoint of the initial observation (None: the centre of the middle grid)."""
    disturbed_evidence_cap: float | None = Field(4.0, ge=2.0)
    """After a manipulation, occupancy and class evidence in the voxels its prediction changed (dilated
    by ``disturbed_margin_voxels``) is shrunk towards the prior until alpha + beta <= this, keeping
    which side of 0.5 each expected occupancy is on, so later views can overturn a wrong prediction and
    IG looks there again; 2 resets them to the prior (unknown). None: the belief is the prediction as
    is, the paper's rule (``examples/mem-rules.yaml``; why: docs/explanation/msas.md)."""
    disturbed_margin_voxels: Int = Field(2, ge=0, le=10)
    """Dilation (voxels) of the changed mask for ``disturbed_evidence_cap`` and ``failed_manipulation_cap``."""
    failed_manipulation_cap: float = Field(4.0, ge=2.0)
    """A manipulation that reports failure (a grasp that lifted nothing, a push stopped short) does not
    write its prediction, which is that of the action succeeding: the belief stays the one before the
    action, with the evidence of the voxels the prediction would have changed (dilated by
    ``disturbed_margin_voxels``) shrunk until alpha + beta <= this, so the following views decide
    what really happened (2: back to the prior)."""
    fall_tilt_deg: float = Field(FALL_TILT_DEG, gt=0.0, lt=90.0)
    """An object whose up axis a manipulation tilted more than this has fallen over; once an object
    fell or left the shelf, manipulation stops for the episode ([MEM])."""

    @model_validator(mode="after")
    def _window(self) -> MSASConfig:
        lo, hi = self.manipulation_window
        if lo < 0 or hi < lo:
            raise ValueError("manipulation_window must be (first, last) with 0 <= first <= last")
        return self


class RunConfig(_Strict):
    """Everything one episode needs; ``msmem config show`` prints the resolved form."""

    method: str = DEFAULT_METHOD
    """The preset the config was resolved from (view-only, push-only, grasp-only, no-cdc, ours)."""
    seed: Int = 0
    """Root seed: every random choice of the episode flows from it."""
    steps: Int = Field(40, ge=1, le=1000)
    """T_max: number of actions in the episode."""
    threads: Int = Field(2, ge=1, le=256)
    """Threads for numba and torch inside one episode."""
    grid: GridConfig = GridConfig()
    camera: CameraConfig = CameraConfig()
    gripper: GripperSpec = GripperSpec()
    viewpoints: ViewpointConfig = ViewpointConfig()
    scene: SceneConfig = SceneConfig()
    simulator: ComponentRef = ComponentRef(name="pybullet")
    robot: ComponentRef = ComponentRef(name="floating")
    """The arm that carries the camera and the gripper (docs/explanation/robots.md): ``floating`` (no arm,
    everything reachable), ``panda`` or ``ur5e`` (the view skill proposes only the views its wrist camera
    reaches)."""
    observation_model: ComponentRef = Field(
        default_factory=lambda: ComponentRef.model_validate(library_defaults()["observation_model"]))
    """sigma_o, the observation update (default ``cnabu-map``: ``msmem_core/presets/defaults.yaml``)."""
    skills: list[SkillRef] = Field(
        default_factory=lambda: [SkillRef.model_validate(s) for s in library_defaults()["skills"]], min_length=1)
    effect_models: dict[str, ComponentRef] = Field(
        default_factory=lambda: {k: ComponentRef.model_validate(v)
                                 for k, v in library_defaults().get("effect_models", {}).items()})
    """Per skill name, the effect model of that skill wherever the method uses it and its ``skills``
    entry names none (e.g. ``{push: {name: push-analytic}}``): one file for every method, without
    changing any method's skills. Names no registered skill has are refused. Default: the push and
    grasp models fine-tuned on ``cnabu-map``'s beliefs (``msmem_core/presets/defaults.yaml``)."""
    skill_params: dict[str, dict[str, Any]] = Field(default_factory=dict)
    """Per skill name, parameters merged over that skill's ``params`` wherever the method uses it
    (e.g. ``{push: {clearance_m: 0.01}}``): like ``effect_models``, one file for every method without
    changing any method's skills. Names no registered skill has are refused."""
    class_map: dict[ClassName, ClassName] | None = None
    """For scenes whose classes the learned models were not trained on: each object class of the scene,
    in the scene's order, to a distinct class they know (e.g. ``{cereal: cracker_box, ...}``). Given
    as ``class_map`` to every component whose params take one and set none (the learned belief
    models), so one map serves the observation and the effect models of every method. None: each
    component's own (none by default: the scene's classes must be the trained ones)."""
    objective: list[TermRef] = Field(default_factory=lambda: [TermRef(name="ig")], min_length=1)
    ig: IGConfig = IGConfig()
    msas: MSASConfig = MSASConfig()
    report_steps: list[Annotated[Int, Field(ge=0)]] | None = None
    """Steps after which the belief and ground truth are saved (``belief_step{N}.npz``) for the run
    report; None: the first, middle and last step (0, T/2, T-1). Steps >= ``steps`` are ignored."""

    @model_validator(mode="after")
    def _merge_skill_params(self) -> RunConfig:
        if self.skill_params:
            self.skills = [r.model_copy(update={"params": {**r.params, **self.skill_params[r.name]}})
                           if r.name in self.skill_params else r for r in self.skills]
        return self

    @model_validator(mode="after")
    def _start_view_exists(self) -> RunConfig:
        start, views = self.msas.start_view, self.viewpoints.num_views
        if start is not None and start >= views:
            raise ValueError(f"msas.start_view {start} is not a viewpoint: there are {views} (0 to {views - 1})")
        return self

    def snapshot_steps(self) -> list[int]:
        """The steps whose belief the run folder keeps for the report (sorted, within the episode)."""
        wanted = self.report_steps if self.report_steps is not None else [0, self.steps // 2, self.steps - 1]
        return sorted({s for s in wanted if s < self.steps})

    def grid_spec(self, shelf: Any) -> GridSpec:
        """The episode's grid around the shelf interior; refused (one line) when it would not fit in memory."""
        return check_grid_memory(GridSpec.around_box(shelf.interior_lower, shelf.interior_upper, self.grid.voxel_m,
                                                     self.grid.margin_voxels))


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursively merge ``over`` into a copy of ``base`` (lists and scalars are replaced). A component
    (a mapping with a ``name``) that names another component replaces the one below whole: the other
    component's parameters do not carry over."""
    out = dict(base)
    for k, v in over.items():
        below = out.get(k)
        other = isinstance(v, dict) and isinstance(below, dict) and "name" in v and v["name"] != below.get("name")
        out[k] = deep_merge(below, v) if isinstance(v, dict) and isinstance(below, dict) and not other else v
    return out


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A YAML or JSON mapping; errors name the file."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise UserError(f"cannot read config file {p}: {e.strerror or e}") from e
    try:
        data = load_json(text) if p.suffix == ".json" else load_yaml(text)
    except (ValueError, yaml.YAMLError) as e:
        raise UserError(f"config file {p} is not valid {'JSON' if p.suffix == '.json' else 'YAML'}: {e}") from e
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"config file {p} must hold a mapping at the top level, not {type(data).__name__}")
    return data


def load_generator_config(path: str | Path | None) -> SceneGenConfig:
    """Scene-generator settings from a YAML or JSON file (``SceneGenConfig`` fields; mesh paths relative
    to the file), or the defaults for None; failures raise a ``UserError`` naming the file and the field."""
    if path is None:
        return SceneGenConfig()
    p = Path(path)
    data = read_config_file(p)
    relative_mesh_files(data.get("classes"), p.parent)
    try:
        return SceneGenConfig.model_validate(data)
    except ValidationError as e:
        raise UserError(f"invalid generator settings in {p}: {error_lines(e)}") from e


def preset(method: str) -> dict[str, Any]:
    """The shipped config of a method preset."""
    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; methods: {', '.join(METHODS)}")
    text = resources.files("msmem_core.presets").joinpath(f"{method}.yaml").read_text()
    return load_yaml(text) or {}


def validate_config(data: dict[str, Any], source: str = "config") -> RunConfig:
    try:
        return RunConfig.model_validate(data)
    except ValidationError as e:
        raise UserError(f"invalid {source}: {error_lines(e)}") from e


def _relative_to(data: dict[str, Any], folder: Path) -> dict[str, Any]:
    """The config file's paths (``viewpoints.poses_file``, the generator's mesh files) made relative to
    the file's folder."""
    scene = data.get("scene")
    if isinstance(scene, dict) and isinstance(scene.get("generator"), dict):
        relative_mesh_files(scene["generator"].get("classes"), folder)
    vp = data.get("viewpoints")
    if isinstance(vp, dict) and isinstance(vp.get("poses_file"), str) and not Path(vp["poses_file"]).is_absolute():
        return data | {"viewpoints": vp | {"poses_file": str(folder / vp["poses_file"])}}
    return data


def load_config(
    method: str | None = None, config_file: str | Path | None = None, overrides: dict[str, Any] | None = None
) -> RunConfig:
    """Resolve preset < file < overrides into a validated ``RunConfig``."""
    data: dict[str, Any] = library_defaults()
    sources = ["library defaults"]
    file_data = read_config_file(config_file) if config_file else {}
    chosen = method or file_data.get("method") or DEFAULT_METHOD
    data = deep_merge(data, preset(chosen))
    sources.append(f"preset {chosen}")
    if config_file:
        data = deep_merge(data, _relative_to(file_data, Path(config_file).parent))
        sources.append(str(config_file))
    if overrides:
        data = deep_merge(data, overrides)
        sources.append("command-line flags")
    data["method"] = chosen if method or "method" not in file_data else file_data["method"]
    return validate_config(data, "config (" + " < ".join(sources) + ")")
