"""The grasp skill (UGS, paper sec. "Uncertainty-informed grasp selection") and its grasp learning
(sec. "Full-Evidential Grasp Learning").

Run time (what an episode imports):

- ``plugin``: the ``grasp`` skill and the ``grasp-analytic`` effect model; ``commands``: the CLI
  commands (``msmem_commands`` hook; bodies import ``learn`` on use).
- ``skill``, ``fusion`` (FE-UMGF), ``fpp``, ``geometric``, ``planning``, ``effect``.
- ``vmf``: the von Mises-Fisher distribution on S^2 (normaliser C(kappa), log-density, sampling).
- ``backbone``: a PTv3-style serialised point transformer in plain PyTorch.
- ``fevmf``: FE-vMF, per-point evidential grasp heads, the approach projection (eq. proj) and the
  executable grasp pose; ``weights``: loading FE-vMF weights (sha256-checked), nothing of training.
- ``metrics``: AUROC and angular errors (used by training and evaluation).
- ``antipodal``: antipodal ground-truth grasps per object class, cached, and their collision-free
  subset in a shelf scene (training data and tests only).

Learning (``learn``, never imported by an episode): ``datagen`` (``msmem datagen grasp``),
``losses`` (the composite FE-vMF loss, eq. fevmf_loss), ``training`` (``msmem train fe-vmf``),
``evaluation`` (``msmem eval fe-vmf``), ``modelcard`` and ``bench`` (``msmem bench-grasp``).
"""

import msmem_core as _msmem_core  # noqa: F401 - sets the OpenMP wait policy before torch loads
