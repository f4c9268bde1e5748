"""Spec records that hooks yield: small frozen dataclasses naming a component and its config model."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict

from msmem_core.errors import PluginError

_NAME = re.compile(r"^[a-z][a-z0-9_-]*$")


class NoConfig(BaseModel):
    """Config model of a component without parameters."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class _Spec:
    name: str
    factory: Callable[[Any], Any]
    """Called with a validated instance of ``config_model``; returns the component."""
    config_model: type[BaseModel] = NoConfig
    description: str = ""

    kind = "component"

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", self.name.strip().lower())
        if not _NAME.match(self.name):
            raise PluginError(f"{self.kind} name {self.name!r} must be lower-case letters, digits, '-' or '_'")
        extra = self.config_model.model_config.get("extra")
        if extra != "forbid":
            raise PluginError(f"{self.kind} {self.name!r}: config model {self.config_model.__name__} "
                              "must set extra='forbid'")


@dataclass(frozen=True)
class SkillSpec(_Spec):
    effect_model: str | None = None
    """Default belief model predicting this skill's effect (None for perception skills)."""
    kind = "skill"


@dataclass(frozen=True)
class BeliefModelSpec(_Spec):
    roles: frozenset[str] = field(default_factory=lambda: frozenset({"observe"}))
    """``observe`` (sigma_o) and/or ``effect`` (sigma_p, sigma_g, ...)."""
    kind = "belief model"


@dataclass(frozen=True)
class SimulatorSpec(_Spec):
    extra: str | None = None
    """Optional dependency group (``pip install 'msmem[extra]'``) the backend needs."""
    kind = "simulator"


@dataclass(frozen=True)
class ObjectiveTermSpec(_Spec):
    kind = "objective term"


@dataclass(frozen=True)
class RobotSpec(_Spec):
    """A robot (``msmem_core.interfaces.Robot``): the arm that carries the camera and the gripper."""

    kind = "robot"


@dataclass(frozen=True)
class CommandSpec:
    """A command a plugin adds to the ``msmem`` command line (conda's ``CondaSubcommand``)::

        CommandSpec(name="nudge-stats", action=nudge_stats, summary="Statistics of nudges", group="eval")

    adds ``msmem eval nudge-stats``. Keep the plugin module cheap to import: import what the command
    needs inside its body.
    """

    name: str
    """The command's name within its group (lower-case letters, digits, '-' or '_')."""
    action: Callable[..., Any]
    """A function with typer-annotated parameters (one command; its docstring is the ``--help``
    text), or a ``typer.Typer`` (a group of commands)."""
    summary: str
    """One line, shown in the command list of ``msmem --help`` or ``msmem GROUP --help``."""
    group: str | None = None
    """The group it joins: ``datagen``, ``train``, ``eval``, ``perf``, ``scene``, ``config`` or
    ``docs``; None for a top-level command (``msmem NAME``)."""

    kind = "command"

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", self.name.strip().lower())
        if not _NAME.match(self.name):
            raise PluginError(f"command name {self.name!r} must be lower-case letters, digits, '-' or '_'")
        if self.group is not None and not _NAME.match(self.group):
            raise PluginError(f"command {self.name!r}: group {self.group!r} must be a command group's name or None")
        if not callable(self.action):
            raise PluginError(f"command {self.name!r}: action must be a function or a typer.Typer, "
                              f"not {type(self.action).__name__}")
        summary = self.summary.strip()
        if not summary or "\n" in summary:
            raise PluginError(f"command {self.name!r}: summary must be one non-empty line")
        object.__setattr__(self, "summary", summary)

    @property
    def path(self) -> str:
        """``GROUP NAME`` or ``NAME``: how it is typed after ``msmem``."""
        return f"{self.group} {self.name}" if self.group else self.name


def missing_extra_factory(kind: str, name: str, extra: str, error: BaseException) -> Callable[[Any], Any]:
    """A factory for a backend whose library failed to import: it registers, and says what to install when used."""

    def factory(_config: Any) -> Any:
        raise PluginError(
            f"{kind} {name!r} needs the optional dependency group '{extra}': "
            f"pip install 'msmem[{extra}]' (import failed: {error})"
        )

    return factory
