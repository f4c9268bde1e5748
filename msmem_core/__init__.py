"""msmem: Multi-Skill Manipulation-Enhanced Mapping as a plugin framework.

The core defines the interfaces (``msmem_core.interfaces``), the plugin manager
(``msmem_core.plugins``), the evidential belief map, the IG service, the MSAS loop, scenes,
ground truth, metrics, the runner and the CLI. Skills, belief models, objective terms and
simulator backends are plugins registered through the ``msmem`` entry-point group.

Importing the package has no side effects. A process that runs episodes calls
``msmem_core.util.threads.configure_threads()`` before torch or numba load their OpenMP runtime (the
``msmem`` command and the runner do).
"""

__version__ = "0.1.0"
