"""Fixtures for the integration tests: the engine's live-link fixtures
(``tests/engine/live/conftest.py``) and the add-on registered in the ``bpy`` module."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests.engine.live.conftest import (  # noqa: F401  (fixtures used here too)
    RawViewer,
    box_scene_dir,
    box_twin_factory,
    raw_viewer,
    wire,
)

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

LAB_BLEND = ROOT / "blend_scenes" / "aces_lab" / "aces_lab.blend"
LAB_SCENE = ROOT / "blend_scenes" / "aces_lab" / "scene"


@pytest.fixture(scope="module")
def addon_module():
    """The add-on registered in the ``bpy`` module (skips without bpy)."""
    bpy = pytest.importorskip("bpy")
    import addon

    if not hasattr(bpy.types.Scene, "isac_live"):
        addon.register()
    return addon


@pytest.fixture
def blank_scene(addon_module):
    """The current Blender scene with the live view cleared and every object removed."""
    import bpy

    from addon import live_view

    live_view.clear(bpy.context.scene)
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    return bpy.context.scene
