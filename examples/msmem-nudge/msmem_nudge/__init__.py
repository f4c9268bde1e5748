"""msmem-nudge: a third-party msmem plugin package (copy it to start your own).

It adds a skill (``nudge``: push an object's top sideways), its analytic effect model
(``nudge-effect``) and an objective term (``travel-cost``), registered through the ``msmem``
entry-point group in ``pyproject.toml``; msmem itself is not touched.
"""

__version__ = "0.1.0"
