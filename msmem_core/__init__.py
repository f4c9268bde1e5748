"""msmem: Multi-Skill Manipulation-Enhanced Mapping as a plugin framework.

The core defines the interfaces (``msmem_core.interfaces``), the plugin manager
(``msmem_core.plugins``), the evidential belief map, the IG service, the MSAS loop, scenes,
ground truth, metrics, the runner and the CLI. Skills, belief models, objective terms and
simulator backends are plugins registered through the ``msmem`` entry-point group.
"""

__version__ = "0.1.0"

import os as _os
import sys as _sys

# numba probes TBB first and warns when the installed one is too old; OpenMP is what we use.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
if "numba" in _sys.modules:  # imported before us: its config has already read the environment
    _sys.modules["numba"].config.THREADING_LAYER = _os.environ["NUMBA_THREADING_LAYER"]
