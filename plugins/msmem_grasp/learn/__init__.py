"""FE-vMF learning, apart from the grasp skill's run time: ``datagen`` (training data), ``losses``,
``training``, ``evaluation``, ``modelcard`` (the weights' model card) and ``bench`` (``msmem bench-grasp``:
grasps executed in the simulator). The skill loads weights through ``msmem_grasp.weights`` only.
"""
