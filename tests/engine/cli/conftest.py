"""Fixtures for the command-line tests: small real scene folders, the live-link test
viewer (``tests/engine/live/conftest.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.engine.live.conftest import (  # noqa: F401  (fixtures used here too)
    box_scene_dir,
    raw_viewer,
    wire,
)
from tests.engine.robots.test_agent import folder as two_robot_room  # noqa: F401  (fixture)

ROOT = Path(__file__).resolve().parents[3]
#: The bundled lab's scene folder.
LAB = ROOT / "blend_scenes" / "aces_lab" / "scene"


@pytest.fixture(scope="session")
def lab(tmp_path_factory):
    """The bundled lab in miniature (two APs, a robot), with a light tracer."""
    from isac_twin.scene.synthetic import two_ap_lab

    return two_ap_lab(tmp_path_factory.mktemp("cli") / "lab",
                      tracer={"samples_per_src": 10000, "max_depth": 1})
