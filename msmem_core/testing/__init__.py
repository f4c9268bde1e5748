"""Testing kit for msmem and its plugins.

- ``msmem_core.testing.fixtures`` (auto-loaded as a pytest plugin): ``plugin_manager`` (a fresh,
  fully loaded manager per test), ``bare_plugin_manager`` (nothing loaded) and ``fake_simulator``.
- ``FakeSimulator``: a tiny in-memory backend for unit tests of loops, never for a feature.
- Builders (``msmem_core.testing.builders``): ``default_workspace``, ``belief_with_boxes``,
  ``belief_of_scene``, ``small_ig``, ``decision_context`` and ``one_decision`` (one MSAS decision
  with your skills, in a unit test).
- Conformance suites (``msmem_core.testing.conformance``): ``simulator_conformance(factory)``,
  ``skill_conformance(factory, name)``, ``effect_model_conformance(factory, actions_for)`` and
  ``observation_model_conformance(factory)``: what a backend, a skill, an effect model or an
  observation model runs to prove it follows its interface and its conventions;
  ``robot_conformance(factory)`` (``msmem_core.testing.robot_conformance``) the same for a robot, its
  answers verified by an independent forward kinematics of its URDF.
"""

from msmem_core.testing.builders import (
    belief_of_scene,
    belief_with_boxes,
    conformance_scene,
    decision_context,
    default_objective,
    default_workspace,
    one_decision,
    small_ig,
    small_viewpoints,
)
from msmem_core.testing.conformance import simulator_conformance
from msmem_core.testing.fake import FakeSimulator
from msmem_core.testing.plugin_conformance import (
    ConformanceError,
    ConformanceUsageError,
    SkillReport,
    check_actions,
    check_base_unchanged,
    check_manipulation_gate,
    check_outcome,
    check_prediction,
    check_reproducible,
    check_updated_belief,
    effect_model_conformance,
    observation_model_conformance,
    skill_conformance,
)
from msmem_core.testing.robot_conformance import RobotReport, check_answer, robot_conformance

__all__ = [
    "ConformanceError",
    "ConformanceUsageError",
    "FakeSimulator",
    "RobotReport",
    "SkillReport",
    "belief_of_scene",
    "belief_with_boxes",
    "check_actions",
    "check_answer",
    "check_base_unchanged",
    "check_manipulation_gate",
    "check_outcome",
    "check_prediction",
    "check_reproducible",
    "check_updated_belief",
    "conformance_scene",
    "decision_context",
    "default_objective",
    "default_workspace",
    "effect_model_conformance",
    "observation_model_conformance",
    "one_decision",
    "robot_conformance",
    "simulator_conformance",
    "skill_conformance",
    "small_ig",
    "small_viewpoints",
]
