"""The plugin manager: safe entry-point loading, duplicate detection and component building."""

from __future__ import annotations

import importlib
import importlib.metadata as md
import os
import sys
import warnings
import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, TypeVar

import pluggy
from pydantic import BaseModel, Field, ValidationError

from msmem_core.errors import ComponentFailure, PluginError, UserError
from msmem_core.plugins.hookspec import PROJECT, MsmemSpecs
from msmem_core.plugins.types import (
    BeliefModelSpec,
    CommandSpec,
    ObjectiveTermSpec,
    RobotSpec,
    SimulatorSpec,
    SkillSpec,
    _Spec,
)
from msmem_core.util.validation import MODEL_CONFIG, loose_scalar, non_finite
from msmem_core.world.scene import CLASS_NAMES, ClassSpec

ENTRY_POINT_GROUP = "msmem"
BUILTIN_DISTRIBUTION = "msmem"
KINDS: dict[str, str] = {
    "skill": "msmem_skills",
    "belief-model": "msmem_belief_models",
    "simulator": "msmem_simulators",
    "objective-term": "msmem_objective_terms",
    "robot": "msmem_robots",
}
S = TypeVar("S", bound=_Spec)


class PluginLoadWarning(UserWarning):
    """A plugin could not be loaded; the others still are."""


_shown: set[str] = set()
"""Plugin warnings this process has printed (``show_warning``)."""


def show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                 file: Any = None, line: str | None = None) -> None:
    """A ``warnings.showwarning`` for msmem's processes (the command line, executor workers): a
    :class:`PluginLoadWarning` as one ``msmem: warning: ...`` line on stderr, once per process (every
    plugin manager a run makes loads the plugins again); other warnings as Python prints them."""
    if not issubclass(category, PluginLoadWarning):
        _python_show_warning(message, category, filename, lineno, file, line)
    elif (text := str(message)) not in _shown:
        _shown.add(text)
        print(f"msmem: warning: {text}", file=sys.stderr if file is None else file, flush=True)


_python_show_warning = warnings.showwarning


class ComponentRef(BaseModel):
    """A reference to a plugin component in config: its registered name and its parameters."""

    model_config = MODEL_CONFIG

    name: str = Field(min_length=1)
    """Registered name of the component (``msmem plugins`` lists them)."""
    params: dict[str, Any] = Field(default_factory=dict)
    """Its parameters, validated against the component's own config model."""


@dataclass(frozen=True)
class Registered:
    """A spec with the plugin and distribution it came from."""

    spec: _Spec
    plugin: str
    distribution: str


@dataclass(frozen=True)
class RegisteredCommand:
    """A command spec with the plugin and distribution it came from."""

    spec: CommandSpec
    plugin: str
    distribution: str


@dataclass(frozen=True)
class Component:
    """A component the plugin manager built: its kind and registered name, and the plugin and
    distribution that provide it."""

    kind: str
    name: str
    plugin: str
    distribution: str

    def __str__(self) -> str:
        return f"{self.kind} {self.name!r} (plugin {self.plugin!r} from {self.distribution})"


_built: dict[int, tuple[weakref.ref[Any], Component]] = {}
"""Every component ``MsmemPluginManager.build`` made in this process and is still alive, by ``id``."""


def _remember(obj: Any, component: Component) -> None:
    key = id(obj)

    def forget(_: weakref.ref[Any]) -> None:
        _built.pop(key, None)

    try:
        ref = weakref.ref(obj, forget)
    except TypeError:  # an object without weak references (``__slots__``): not traced
        return
    _built[key] = (ref, component)


def built_component(obj: Any) -> Component | None:
    """The component ``obj`` is, if a plugin manager built it (None otherwise)."""
    entry = _built.get(id(obj))
    return entry[1] if entry is not None and entry[0]() is obj else None


def failed_component(error: BaseException) -> Component | None:
    """The component whose code raised ``error``: the innermost frame of its traceback that runs a method
    of an object a plugin manager built (a component calling msmem's own code is still the one named).
    None when no component's method is on the traceback (the error is msmem's own)."""
    found = None
    tb = error.__traceback__
    while tb is not None:  # outermost to innermost: the last one found is the innermost
        obj = tb.tb_frame.f_locals.get("self")
        if obj is not None and (c := built_component(obj)) is not None:
            found = c
        tb = tb.tb_next
    return found


def _flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() not in ("", "0", "false", "no")


def _reason(e: BaseException) -> str:
    """``Type: message`` on one line (what ``msmem plugins`` lists for a failed plugin)."""
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


class MsmemPluginManager(pluggy.PluginManager):
    """pluggy manager with typed accessors. Create one per process with ``get_plugin_manager``."""

    def __init__(self) -> None:
        super().__init__(PROJECT)
        self.add_hookspecs(MsmemSpecs)
        self.distributions: dict[str, str] = {}
        """Plugin name -> distribution that provided it."""
        self.load_errors: dict[str, str] = {}
        """Plugin name -> why it failed to load or was skipped (one line; ``msmem plugins`` lists them)."""
        self.failed_distributions: dict[str, str] = {}
        """Plugin name (key of ``load_errors``) -> the distribution it came from."""
        self.command_errors: dict[str, str] = {}
        """Plugin name -> why its ``msmem_commands`` hook failed (its commands are left out)."""
        self._cache: dict[str, dict[str, Registered]] = {}
        self._commands: list[RegisteredCommand] | None = None
        self._classes: dict[str, ClassSpec] | None = None
        self.class_sources: dict[str, tuple[str, str]] = {}
        """Object class name -> (plugin, distribution) that declared it."""
        if _flag("MSMEM_TRACE_PLUGINS"):
            self.trace.root.setwriter(lambda s: print(s, end="", file=sys.stderr))
            self.enable_tracing()

    # ------------------------------------------------------------------------------------ loading
    def register_plugin(self, plugin: object, name: str, distribution: str) -> None:
        """Register a module or object as a plugin; hook signatures are checked against the specs."""
        try:
            self.register(plugin, name=name)
        except (pluggy.PluginValidationError, ValueError) as e:
            raise PluginError(f"plugin {name!r} from {distribution} is invalid: {e}") from e
        self.distributions[name] = distribution
        self._cache.clear()
        self._commands = None
        self._classes = None

    def _skip(self, key: str, distribution: str, message: str, reason: str, stacklevel: int = 3) -> None:
        """Record why a plugin is left out (``load_errors``, listed by ``msmem plugins``) and warn."""
        self.load_errors[key] = reason
        self.failed_distributions[key] = distribution
        warnings.warn(message, PluginLoadWarning, stacklevel=stacklevel)

    def _load_one(self, name: str, target: str, distribution: str, loader: Any) -> None:
        if self.is_blocked(name):
            return
        if self.has_plugin(name):
            same_module = getattr(self.get_plugin(name), "__name__", None) == target.partition(":")[0]
            if self.distributions.get(name) != distribution and not same_module:  # never a silent replacement
                other = self.distributions.get(name, "?")
                reason = f"the name is taken by plugin {name!r} from {other}"
                self._skip(f"{distribution}:{name}", distribution,
                           f"msmem plugin {name!r} from {distribution} is refused: {reason}", f"refused: {reason}")
            return
        try:
            plugin = loader()
        except KeyboardInterrupt:
            raise
        except BaseException as e:  # SystemExit too: a broken plugin must not take the others down
            self._skip(name, distribution, f"msmem plugin {name!r} ({target}, from {distribution}) failed to load "
                       f"and is skipped: {_reason(e)}", _reason(e))
            return
        try:
            self.register_plugin(plugin, name, distribution)
        except PluginError as e:
            self._skip(name, distribution, f"msmem plugin {name!r} (from {distribution}) is skipped: {e}", str(e))

    def load_entrypoints(self, group: str = ENTRY_POINT_GROUP) -> None:
        """Load every ``msmem`` entry point. With ``MSMEM_DISABLE_PLUGIN_AUTOLOAD`` set, only built-ins load.

        msmem's own distribution loads first, the others in name order, so a third-party plugin named
        like a built-in one is the one refused, whatever the order of ``sys.path``.
        """
        only_builtin = _flag("MSMEM_DISABLE_PLUGIN_AUTOLOAD")
        seen: set[tuple[str, str]] = set()
        dists = sorted(((d.metadata["Name"] or "?", i, d) for i, d in enumerate(md.distributions())),
                       key=lambda t: (t[0] != BUILTIN_DISTRIBUTION, t[0], t[1]))
        for dist_name, _, dist in dists:
            if only_builtin and dist_name != BUILTIN_DISTRIBUTION:
                continue
            for ep in dist.entry_points:
                if ep.group != group or (dist_name, ep.name) in seen:
                    continue
                seen.add((dist_name, ep.name))
                self._load_one(ep.name, ep.value, dist_name, ep.load)

    def load_env_plugins(self, value: str | None = None) -> None:
        """Register uninstalled modules named in ``MSMEM_PLUGINS="name=module[,name=module]"``."""
        value = os.environ.get("MSMEM_PLUGINS", "") if value is None else value
        for item in filter(None, (s.strip() for s in value.split(","))):
            name, sep, module = item.partition("=")
            if not sep or not name.strip() or not module.strip():
                raise PluginError(f"MSMEM_PLUGINS entry {item!r} must look like name=module")
            mod = module.strip()
            self._load_one(name.strip(), mod, "MSMEM_PLUGINS", lambda m=mod: importlib.import_module(m))

    def check(self) -> None:
        """Catch hook implementations that match no spec (typos such as ``msmem_skils``)."""
        try:
            self.check_pending()
        except pluggy.PluginValidationError as e:
            plugin = self.get_name(e.plugin) or "?"
            dist = self.distributions.get(plugin, "?")
            raise PluginError(f"plugin {plugin!r} from {dist}: {e}") from e

    # ------------------------------------------------------------------------------------ results
    def registered(self, kind: str) -> dict[str, Registered]:
        """All specs of one kind ('skill', 'belief-model', 'simulator', 'objective-term', 'robot') by name."""
        if kind not in KINDS:
            raise PluginError(f"unknown component kind {kind!r}; kinds: {', '.join(KINDS)}")
        if kind in self._cache:
            return self._cache[kind]
        hook = getattr(self.hook, KINDS[kind])
        out: dict[str, Registered] = {}
        trace = _flag("MSMEM_TRACE_PLUGINS")
        for impl in reversed(hook.get_hookimpls()):  # registration order
            dist = self.distributions.get(impl.plugin_name, "?")
            try:
                found: Any = impl.function()
                specs = list(found or ())
            except KeyboardInterrupt:
                raise
            except BaseException as e:  # a plugin whose hook fails is skipped, the others are kept
                return self._drop(kind, impl.plugin_name, f"{KINDS[kind]} hook failed: {_reason(e)}")
            if trace:
                names = ", ".join(s.name for s in specs)
                print(f"msmem: {KINDS[kind]}() -> {impl.plugin_name} ({dist}): {names}", file=sys.stderr)
            for spec in specs:
                other = out.get(spec.name)
                if other is None:
                    out[spec.name] = Registered(spec, impl.plugin_name, dist)
                    continue
                if BUILTIN_DISTRIBUTION in (other.distribution, dist) and other.distribution != dist:
                    # never a silent replacement of a built-in: the other distribution's plugin is refused
                    keep, drop = (other.plugin, impl.plugin_name) if dist != BUILTIN_DISTRIBUTION else \
                        (impl.plugin_name, other.plugin)
                    return self._drop(kind, drop, f"its {spec.kind} {spec.name!r} clashes with plugin {keep!r} from "
                                      f"{BUILTIN_DISTRIBUTION}")
                raise PluginError(
                    f"{spec.kind} name {spec.name!r} is registered twice: by plugin {other.plugin!r} "
                    f"from {other.distribution} and by plugin {impl.plugin_name!r} from {dist}"
                )
        self._cache[kind] = out
        return out

    def _drop(self, kind: str, plugin: str, reason: str) -> dict[str, Registered]:
        """Unregister ``plugin`` (named in a warning and in ``load_errors``) and list ``kind`` again."""
        dist = self.distributions.get(plugin, "?")
        self.unregister(name=plugin)
        self.set_blocked(plugin)
        self._cache.clear()
        self._commands = None
        self._skip(plugin, dist, f"msmem plugin {plugin!r} (from {dist}) is skipped: {reason}", reason, stacklevel=4)
        return self.registered(kind)

    def spec(self, kind: str, name: str) -> _Spec:
        table = self.registered(kind)
        if name not in table:
            avail = ", ".join(sorted(table)) or "none"
            raise PluginError(f"no {kind} named {name!r}; available: {avail}")
        return table[name].spec

    def skills(self) -> dict[str, SkillSpec]:
        return {n: r.spec for n, r in self.registered("skill").items()}  # type: ignore[misc]

    def belief_models(self) -> dict[str, BeliefModelSpec]:
        return {n: r.spec for n, r in self.registered("belief-model").items()}  # type: ignore[misc]

    def simulators(self) -> dict[str, SimulatorSpec]:
        return {n: r.spec for n, r in self.registered("simulator").items()}  # type: ignore[misc]

    def objective_terms(self) -> dict[str, ObjectiveTermSpec]:
        return {n: r.spec for n, r in self.registered("objective-term").items()}  # type: ignore[misc]

    def robots(self) -> dict[str, RobotSpec]:
        return {n: r.spec for n, r in self.registered("robot").items()}  # type: ignore[misc]

    def commands(self) -> list[RegisteredCommand]:
        """Every plugin's command specs, in registration order.

        A plugin whose ``msmem_commands`` hook raises, or yields something that is not a
        ``CommandSpec``, is named in a ``PluginLoadWarning`` and in ``command_errors``; its commands are
        left out and everyone else's kept (a broken plugin must not take the command line down). A
        command registered twice at the same place keeps the first, with a warning naming both plugins.
        """
        if self._commands is not None:
            return self._commands
        out: dict[str, RegisteredCommand] = {}
        trace = _flag("MSMEM_TRACE_PLUGINS")
        for impl in self.hook.msmem_commands.get_hookimpls():  # registration order (pluggy calls them in reverse)
            plugin = impl.plugin_name
            dist = self.distributions.get(plugin, "?")
            try:
                result: Any = impl.function()
                specs = list(result or ())
                for spec in specs:
                    if not isinstance(spec, CommandSpec):
                        raise PluginError(f"msmem_commands() must yield CommandSpec records, got {spec!r}")
            except Exception as e:  # a broken plugin must not take the command line down
                self.command_errors[plugin] = f"{type(e).__name__}: {e}"
                warnings.warn(f"msmem plugin {plugin!r} (from {dist}): its msmem_commands hook failed, its commands "
                              f"are left out: {type(e).__name__}: {e}", PluginLoadWarning, stacklevel=2)
                continue
            if trace:
                names = ", ".join(s.path for s in specs)
                print(f"msmem: msmem_commands() -> {plugin} ({dist}): {names}", file=sys.stderr)
            for spec in specs:
                if spec.path in out:
                    other = out[spec.path]
                    warnings.warn(f"command 'msmem {spec.path}' is registered twice: by plugin {other.plugin!r} "
                                  f"from {other.distribution} (kept) and by plugin {plugin!r} from {dist} (left out)",
                                  PluginLoadWarning, stacklevel=2)
                    continue
                out[spec.path] = RegisteredCommand(spec, plugin, dist)
        self._commands = list(out.values())
        return self._commands

    def object_classes(self) -> dict[str, ClassSpec]:
        """Every plugin's object classes by name, in registration order (``msmem_object_classes``).

        A plugin whose hook raises or yields something that is not a ``ClassSpec``, and a class named
        like a built-in or declared by an earlier plugin, are named in a ``PluginLoadWarning`` and left
        out; everyone else's classes are kept.
        """
        if self._classes is not None:
            return self._classes
        out: dict[str, ClassSpec] = {}
        for impl in self.hook.msmem_object_classes.get_hookimpls():  # registration order
            plugin = impl.plugin_name
            dist = self.distributions.get(plugin, "?")
            try:
                found: Any = impl.function()
                specs = list(found or ())
                for spec in specs:
                    if not isinstance(spec, ClassSpec):
                        raise PluginError(f"msmem_object_classes() must yield ClassSpec records, got {spec!r}")
            except Exception as e:
                warnings.warn(f"msmem plugin {plugin!r} (from {dist}): its msmem_object_classes hook failed, its "
                              f"classes are left out: {type(e).__name__}: {e}", PluginLoadWarning, stacklevel=2)
                continue
            for spec in specs:
                if spec.name in CLASS_NAMES or spec.name in out:
                    other = "a built-in class" if spec.name in CLASS_NAMES else \
                        f"declared by plugin {self.class_sources[spec.name][0]!r} (kept)"
                    warnings.warn(f"object class {spec.name!r} of plugin {plugin!r} (from {dist}) is left out: "
                                  f"the name is {other}", PluginLoadWarning, stacklevel=2)
                    continue
                out[spec.name] = spec
                self.class_sources[spec.name] = (plugin, dist)
        self._classes = out
        return out

    # ------------------------------------------------------------------------------------ building
    def validate(self, kind: str, ref: ComponentRef | str, where: str | None = None, **extra: Any) -> BaseModel:
        """``ref.params`` checked against the spec's config model: the component's config, or a
        ``PluginError`` naming the component and the field (``where``: where the config names it).

        ``extra`` supplies run-wide values (camera, gripper, seed) for config fields the user did not set.
        """
        if isinstance(ref, str):
            ref = ComponentRef(name=ref)
        spec = self.spec(kind, ref.name)
        fields = spec.config_model.model_fields
        params = {k: v for k, v in extra.items() if k in fields} | dict(ref.params)
        at = f"{where}.params" if where else "params"
        # whatever the plugin's config model allows: no NaN or infinity, no bool for an int or an int for a bool
        for loc in non_finite(ref.params):
            raise PluginError(f"{kind} {ref.name!r}: {at}.{loc}: Input should be a finite number")
        for name, value in ref.params.items():
            why = loose_scalar(value, fields[name].annotation) if name in fields else None
            if why:
                raise PluginError(f"{kind} {ref.name!r}: {at}.{name}: {why}")
        try:
            return spec.config_model.model_validate(params)
        except ValidationError as e:
            err = e.errors()[0]
            loc = ".".join(str(x) for x in err["loc"])
            raise PluginError(f"{kind} {ref.name!r}: {at}.{loc}: {err['msg']}") from e

    def build(self, kind: str, ref: ComponentRef | str, where: str | None = None, **extra: Any) -> Any:
        """Validate ``ref.params`` (:meth:`validate`) and call the spec's factory.

        ``extra`` supplies run-wide values (camera, gripper, seed) for config fields the user did not set.
        A factory that raises (other than a ``UserError``, which says what the user must change) is a
        :class:`~msmem_core.errors.ComponentFailure` naming the component, its plugin and distribution.
        What is built is remembered (weakly), so that an exception its code raises later is traced to it
        (:func:`failed_component`).
        """
        if isinstance(ref, str):
            ref = ComponentRef(name=ref)
        config = self.validate(kind, ref, where, **extra)
        reg = self.registered(kind)[ref.name]
        component = Component(kind, ref.name, reg.plugin, reg.distribution)
        try:
            built = reg.spec.factory(config)
        except (UserError, KeyboardInterrupt):
            raise
        except Exception as e:
            at = f" ({where})" if where else ""
            raise ComponentFailure(f"{component} failed while being built{at}: {_reason(e)}") from e
        _remember(built, component)
        return built

    def listing(self) -> list[dict[str, Any]]:
        """One row per component: kind, name, distribution, plugin, description, config fields."""
        rows = []
        for kind in KINDS:
            for name, reg in sorted(self.registered(kind).items()):
                schema = reg.spec.config_model.model_json_schema()
                props = schema.get("properties", {})
                rows.append(
                    {
                        "kind": kind,
                        "name": name,
                        "distribution": reg.distribution,
                        "plugin": reg.plugin,
                        "description": reg.spec.description,
                        "config": {k: {kk: v[kk] for kk in ("type", "default", "description") if kk in v}
                                   for k, v in props.items()},
                    }
                )
        for name, cls in self.object_classes().items():
            plugin, dist = self.class_sources[name]
            shape = f"mesh {cls.mesh.file}" if cls.mesh is not None else f"{len(cls.parts)} parts"
            rows.append({"kind": "object-class", "name": name, "distribution": dist, "plugin": plugin,
                         "description": f"object class: {shape}, {cls.mass_kg} kg", "config": {}})
        return rows


def get_plugin_manager(load: bool = True, extra_plugins: Iterable[tuple[str, object]] = ()) -> MsmemPluginManager:
    """A fresh manager with entry points, ``MSMEM_PLUGINS`` and ``extra_plugins`` loaded and checked."""
    pm = MsmemPluginManager()
    if load:
        pm.load_entrypoints()
        pm.load_env_plugins()
    for name, plugin in extra_plugins:
        pm.register_plugin(plugin, name, "<code>")
    pm.check()
    return pm
