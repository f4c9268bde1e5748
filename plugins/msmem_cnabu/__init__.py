"""Learned CNABU belief models (MEM's Calibrated Neural Accelerated Belief Updates): 2.5-D U-Nets for the
observation update (sigma_o) and the push and grasp effects (sigma_p, sigma_g), their data generation,
training, evaluation and the belief-model plugins ``cnabu-observe``, ``cnabu-push``, ``cnabu-grasp``.

- ``network``: the 2.5-D U-Net (height bins as channels, relu + 1 evidence, change map);
- ``features``: belief features, action channels, the shelf's walls;
- ``losses``: digamma expected cross-entropy + annealed KL (Beta and Dirichlet), change BCE;
- ``datagen``: ``msmem datagen cnabu`` (simulated episodes, ``--sim``, -> sharded samples);
- ``training``: ``msmem train cnabu``; ``weights``: loading with sha256 checks;
- ``models``: the belief models; ``evaluation``: ``msmem eval belief-models``;
- ``commands``: the CLI commands (registered by ``plugin.msmem_commands``).
"""

import msmem_core as _msmem_core  # noqa: F401 - sets the OpenMP wait policy before torch loads
