"""Learned CNABU belief models (MEM's Calibrated Neural Accelerated Belief Updates): 2.5-D U-Nets for the
observation update (sigma_o) and the push and grasp effects (sigma_p, sigma_g), the whole-map observation
network, and their learning.

Run time (what an episode imports):

- ``plugin``: the belief models ``cnabu-observe``, ``cnabu-map``, ``cnabu-push``, ``cnabu-grasp``;
  ``commands``: the CLI commands (``msmem_commands`` hook; bodies import ``learn`` on use).
- ``configs``: the belief models' params; ``classmap``: a scene's classes onto the trained ones.
- ``models``: ``cnabu-observe``, ``cnabu-push``, ``cnabu-grasp``; ``mapmodel``: ``cnabu-map``.
- ``network``: the 2.5-D U-Net (height bins as channels, relu + 1 evidence, change map); ``mapnet``: the
  whole-map network (previous belief + one view -> next belief, bounded evidence).
- ``features``: belief features, action channels, the shelf's walls.
- ``weights``: loading weights (both kinds) with sha256 checks, nothing of training.

Learning (``learn``, never imported by an episode): ``datagen`` (``msmem datagen cnabu``: simulated
episodes, ``--sim``, -> sharded samples), ``losses`` (digamma expected cross-entropy + annealed KL, Beta
and Dirichlet, change BCE), ``training`` (``msmem train cnabu``), ``evaluation`` (``msmem eval
belief-models``), ``rollouts``, ``maploss``, ``maptrain`` (``msmem train cnabu-map``) and ``mapeval``
(``msmem eval map``).
"""

import msmem_core as _msmem_core  # noqa: F401 - sets the OpenMP wait policy before torch loads
