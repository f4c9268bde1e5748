"""msmem: Multi-Skill Manipulation-Enhanced Mapping as a plugin framework.

The core defines the interfaces (``msmem_core.interfaces``), the plugin manager
(``msmem_core.plugins``), the evidential belief map, the IG service, the MSAS loop, scenes,
ground truth, metrics, the runner and the CLI. Skills, belief models, objective terms and
simulator backends are plugins registered through the ``msmem`` entry-point group.
"""

__version__ = "0.1.0"
