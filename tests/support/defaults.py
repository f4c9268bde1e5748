"""The analytic models (``examples/analytic.yaml``: the analytic observation update and the effect
models trained on its beliefs), for tests of the machinery around a model (custom classes,
reports, backends, a manipulation executed) that must not depend on which observation model is the
default. Tests of the defaults themselves (``tests/test_golden.py``'s ``library-defaults``) do not use it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msmem_core.config import read_config_file

ANALYTIC: dict[str, Any] = read_config_file(Path(__file__).resolve().parents[2] / "examples" / "analytic.yaml")
