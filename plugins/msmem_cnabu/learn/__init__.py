"""CNABU learning, apart from the belief models' run time: ``datagen`` (``msmem datagen cnabu``: training
data), ``losses`` (the effect and observe networks' evidential losses), ``training`` (``msmem train
cnabu``), ``evaluation`` (``msmem eval belief-models``), and for the whole-map network ``rollouts``
(recorded view sequences and the effect models applied in them), ``maploss``, ``maptrain`` (``msmem
train cnabu-map``) and ``mapeval`` (``msmem eval map``). The belief models load weights through
``msmem_cnabu.weights`` only.
"""
