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
# OpenMP threads (torch's and numba's) sleep at barriers instead of spinning. A spinning thread takes
# its core from the threads still working whenever the machine has more runnable threads than cores
# (two episodes in parallel, or other jobs): FE-vMF inference with 2 torch threads then took 0.5-1.4 s
# instead of 0.05-0.07 s (docs/performance.md). Read when an OpenMP runtime loads, so set before torch/numba.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if "numba" in _sys.modules:  # imported before us: its config has already read the environment
    _sys.modules["numba"].config.THREADING_LAYER = _os.environ["NUMBA_THREADING_LAYER"]
