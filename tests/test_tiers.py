"""The fast tier names modules that exist (a renamed test module must not drop out of it silently)."""

from pathlib import Path

from conftest import UNIT_MODULES


def test_every_unit_module_exists() -> None:
    here = Path(__file__).parent
    missing = sorted(m for m in UNIT_MODULES if not (here / f"{m}.py").exists())
    assert not missing, f"tests/conftest.py UNIT_MODULES names modules that do not exist: {missing}"
    assert len(UNIT_MODULES) >= 30
