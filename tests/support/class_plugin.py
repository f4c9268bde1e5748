"""A plugin that declares object classes (``msmem_object_classes``), for the class-registry tests."""

from collections.abc import Iterable

from msmem_core.plugins import hookimpl
from msmem_core.world.scene import ClassSpec, Part

CHIPS = ClassSpec(name="chips_can", parts=(Part(kind="cylinder", size_m=(0.038, 0.25), position_m=(0.0, 0.0, 0.125)),),
                  mass_kg=0.2, color_rgb=(0.9, 0.6, 0.1))
BRICK = ClassSpec(name="toy_brick", parts=(Part(kind="box", size_m=(0.06, 0.03, 0.04), position_m=(0.0, 0.0, 0.02)),),
                  mass_kg=0.05)


@hookimpl
def msmem_object_classes() -> Iterable[ClassSpec]:
    yield CHIPS
    yield BRICK
    yield ClassSpec(name="mug", parts=BRICK.parts)  # a built-in's name: left out with a warning
