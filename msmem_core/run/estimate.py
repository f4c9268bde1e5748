"""What an episode will cost, from its grid and its scene's objects, before anything is built: memory and
the time of the work that grows with the objects; a scene above the limits is refused in one line.

The grid's memory is ``bytes_per_voxel`` per voxel (``msmem_core.map.belief``, which refuses a grid too
large for memory by itself). What grows with the objects was measured on this project's 2-core machine
with a lattice of tuna cans on a 3 m x 2 m shelf (2 cm voxels, view-only, 2 steps; 150 and 600 objects:
10.1 s and 38.5 s to reset and score the start, peak memory 616 and 639 MB, placement checks 0.13 s and
1.32 s):

- checking the placements (every pair of objects): ``PLACEMENT_S_PER_PAIR`` per pair;
- resetting the simulator and voxelising and ray-casting the ground truth (``MetricTracker``): about
  ``GROUND_TRUTH_S_PER_OBJECT`` per object at the start, and again after every step that moved an
  object (at most every step of a method with a manipulation skill);
- memory: ``BYTES_PER_OBJECT`` per object (twice the measured 0.05 MB).

The time of the steps themselves (views, IG, effect models) depends on the method and the grid and is
not part of the estimate.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from msmem_core.errors import UserError
from msmem_core.map.belief import bytes_per_voxel, memory_limit_bytes
from msmem_core.world.grid import GridSpec

PLACEMENT_S_PER_PAIR = 4e-6
GROUND_TRUTH_S_PER_OBJECT = 0.065
BYTES_PER_OBJECT = 100_000
MINUTES_VAR = "MSMEM_MAX_SCENE_MINUTES"
"""Environment variable: the most minutes of object work a run may be estimated at (default
``DEFAULT_MAX_MINUTES``)."""
DEFAULT_MAX_MINUTES = 30.0
REPORT_ABOVE_S = 60.0
"""Estimates of more object work than this are worth a line before the run starts."""


@dataclass(frozen=True)
class Estimate:
    """The estimated cost of an episode: memory (grid and objects) and seconds of object work."""

    objects: int
    voxels: int
    memory_bytes: int
    start_s: float
    """Placement checks, the simulator's reset and the first ground truth."""
    per_step_s: float
    """Ground truth again after a step that moved objects (0 for a method that never manipulates)."""
    steps: int

    @property
    def seconds(self) -> float:
        return self.start_s + self.steps * self.per_step_s

    def describe(self) -> str:
        steps = f" + {self.steps} x {_duration(self.per_step_s)} after manipulations" if self.per_step_s else ""
        return (f"{self.objects} objects on a grid of {self.voxels:,} voxels: about {_gib(self.memory_bytes)} and "
                f"{_duration(self.seconds)} of work for the objects ({_duration(self.start_s)} to start{steps})")


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB"


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.0f} min" if s >= 60 else f"{s:.0f} s"


def estimate(objects: int, grid: GridSpec, num_classes: int, steps: int, manipulates: bool) -> Estimate:
    """The :class:`Estimate` of an episode with ``objects`` on ``grid`` for ``steps`` steps
    (``manipulates``: the method has a manipulation skill, so objects may move at every step)."""
    start = PLACEMENT_S_PER_PAIR * objects * (objects - 1) / 2 + GROUND_TRUTH_S_PER_OBJECT * objects
    return Estimate(objects, grid.size, grid.size * bytes_per_voxel(num_classes) + BYTES_PER_OBJECT * objects,
                    start, GROUND_TRUTH_S_PER_OBJECT * objects if manipulates else 0.0, steps)


def max_minutes() -> float:
    """The limit on estimated object work, in minutes (``MSMEM_MAX_SCENE_MINUTES``, default 30)."""
    text = os.environ.get(MINUTES_VAR, "").strip()
    if not text:
        return DEFAULT_MAX_MINUTES
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value > 0:
        raise UserError(f"{MINUTES_VAR}={text!r}: expected a positive number of minutes")
    return value


def check_estimate(est: Estimate, scene: str) -> Estimate:
    """``est``, or a one-line ``UserError`` naming ``scene`` and the estimate when it needs more memory than
    half of physical memory or more object work than :func:`max_minutes`."""
    limit_b, limit_m = memory_limit_bytes(), max_minutes()
    if est.memory_bytes > limit_b:
        raise UserError(f"{scene}: {est.describe()}, more memory than the limit of {_gib(limit_b)} (half of "
                        "physical memory); use fewer objects, a larger grid.voxel_m or a smaller shelf")
    if est.seconds > 60 * limit_m:
        raise UserError(f"{scene}: {est.describe()}, more than the limit of {limit_m:g} min; use fewer objects or "
                        f"steps, or raise the limit with {MINUTES_VAR}")
    return est
