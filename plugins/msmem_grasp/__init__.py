"""Grasp learning for UGS (paper sec. "Full-Evidential Grasp Learning").

- ``vmf``: the von Mises-Fisher distribution on S^2 (normaliser C(kappa), log-density, sampling).
- ``backbone``: a PTv3-style serialised point transformer in plain PyTorch.
- ``fevmf``: FE-vMF, per-point evidential grasp heads, the approach projection (eq. proj) and the
  executable grasp pose.
- ``losses``: the composite FE-vMF loss (eq. fevmf_loss): vMF NLL for a_hat and b, evidential Beta
  loss for the affordance, L1 on the width.
- ``antipodal``: antipodal ground-truth grasps per object class, cached, and their collision-free
  subset in a shelf scene.
"""

import msmem_core as _msmem_core  # noqa: F401 - sets the OpenMP wait policy before torch loads
