"""The second bundled room: blend_scenes/l_office, built by its script through the add-on."""

from __future__ import annotations

import runpy
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = [pytest.mark.blender, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
ROOM_DIR = ROOT / "blend_scenes" / "l_office"


@pytest.fixture(scope="module")
def office(addon_module, reset_scene, tmp_path_factory):
    from addon.exporter import export_scene

    build = SimpleNamespace(**runpy.run_path(str(ROOM_DIR / "build_l_office.py")))
    scene = build.build(bpy.context.scene)
    folder = tmp_path_factory.mktemp("l_office")
    export_scene(scene, folder)
    yield folder, build
    reset_scene()


def test_committed_scene_folder_is_current(office):
    """blend_scenes/l_office/scene equals a fresh export (USD aside: not byte-deterministic)."""
    folder = office[0]
    committed = ROOM_DIR / "scene"
    fresh = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    stored = sorted(p.relative_to(committed).as_posix() for p in committed.rglob("*")
                    if p.is_file())
    assert fresh == stored
    for rel in fresh:
        if not rel.endswith(".usdc"):
            assert (folder / rel).read_bytes() == (committed / rel).read_bytes(), rel


def test_office_is_an_l_at_5_8_ghz_with_tags_and_a_curve_path(office):
    folder, build = office
    data = tomllib.loads((folder / "twin.toml").read_text())
    assert data["scene"]["frequency_hz"] == 5.8e9
    room = data["room"]
    assert {"Room_Floor", "Room_Ceiling", "Room_Window", "Glass_Partition"} <= set(room["shell"])
    assert {f"Room_Wall_{i}" for i in range(1, 7)} <= set(room["shell"])
    assert "Desk_1" in room["furniture"] and "Rack_1" in room["furniture"]
    robot = next(d for d in data["devices"] if d["name"] == "robot1")
    assert robot["path"] == {"kind": "polyline", "closed": True,
                             "waypoints": [list(p) for p in build.PATH]}
    from isac_twin import load_scene
    from isac_twin.scene.room import room_parts

    s = load_scene(folder, load_sionna=False)  # free space checked: devices and the path
    p = room_parts(s)
    assert set(p.tagged) == set(s.objects)  # every object tagged by the add-on's tools
    assert len(p.walls) == 6 + 2 and p.floor == ("Room_Floor",)
