"""Scene folders for the ray-tracing tests (isac_twin.scene.synthetic, no Blender)."""

from __future__ import annotations

import pytest

import isac_twin  # noqa: F401 - sets DRJIT_LIBLLVM_PATH before mitsuba loads
from isac_twin.scene.synthetic import furnished_room


@pytest.fixture(scope="session")
def room_folder(tmp_path_factory):
    return furnished_room(tmp_path_factory.mktemp("room"))


@pytest.fixture(scope="session")
def room_scene(room_folder):
    from isac_twin import load_scene

    return load_scene(room_folder)


@pytest.fixture(scope="session")
def room_grid(room_scene):
    from isac_twin.raytrace.grid import trace_grid

    return trace_grid(room_scene, spacing=0.25, progress=False)
