"""Class maps: a scene's object classes onto the classes a learned model's weights were trained on (the
``class_map`` param of ``cnabu-map``, ``cnabu-push`` and ``cnabu-grasp``, or a run config's top-level
``class_map``, which the run gives to each of them).

The model then takes the scene's classes (background, then the map's scene classes in order), its
network sees and predicts the mapped trained classes, and the evidence of trained classes no scene
class maps to is dropped."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.world.scene import counted_classes


def onto_slots(a: NDArray[Any], index: NDArray[np.int64], num_classes: int, fill: Any, axis: int = 0) -> NDArray[Any]:
    """``a`` with its class axis ``axis`` spread onto ``num_classes`` slots: class ``c`` to slot ``index[c]``,
    every other slot ``fill`` (a class map's scene classes onto the trained ones)."""
    shape = list(a.shape)
    shape[axis] = num_classes
    out = np.full(shape, fill, dtype=a.dtype)
    out[(slice(None),) * axis + (index,)] = a
    return out


def mapped_classes(class_map: dict[str, str], trained: tuple[str, ...] | None, component: str = "cnabu-map"
                   ) -> tuple[tuple[str, ...], NDArray[np.int64]]:
    """The classes a ``class_map`` makes the model take (background, then the map's scene classes in order)
    and, per one of them, the index of the trained class it maps to; refused in one line naming
    ``component`` and the offending keys when the map names a class the weights do not know, maps two
    classes to one, or maps background."""
    if trained is None:
        raise UserError(f"{component}: class_map needs weights that record the classes they were trained on, "
                        "and these record none; name weights made by `msmem train` or drop class_map")
    if "background" in class_map:
        raise UserError(f"{component}: class_map maps background, which is always itself; remove that key")
    if nothing := [k for k, m in class_map.items() if m == "background"]:
        raise UserError(f"{component}: class_map maps {', '.join(nothing)} to background, which is no object class; "
                        f"map each scene class to one the weights know: {counted_classes(trained)}")
    wrong = [f"{k} to {m}" for k, m in class_map.items() if m not in trained[1:]]
    if wrong:
        raise UserError(f"{component}: class_map maps {', '.join(wrong)}, which the weights do not know; "
                        f"they know {counted_classes(trained)}")
    targets = list(class_map.values())
    if twice := sorted({m for m in targets if targets.count(m) > 1}):
        keys = "; ".join(f"{' and '.join(k for k, v in class_map.items() if v == m)} to {m}" for m in twice)
        raise UserError(f"{component}: class_map maps {keys}; map each scene class to a class of its own "
                        f"(the weights know {counted_classes(trained)})")
    index = np.array([0, *(trained.index(m) for m in targets)], dtype=np.int64)
    return ("background", *class_map), index
