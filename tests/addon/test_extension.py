"""The add-on as a Blender extension: validate, build the zip, install it and use it.

Uses Blender's own extension tool shipped inside the bpy module
(``<bpy>/<version>/scripts/addons_core/bl_pkg/cli/blender_ext.py``). The
install runs in a fresh interpreter with a temporary BLENDER_USER_RESOURCES:
the extension registers the same classes as the legacy add-on this session
already registered, and it must not touch real user preferences.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = [pytest.mark.blender, pytest.mark.slow]

HERE = Path(__file__).resolve().parent
ADDON_DIR = HERE.parents[1] / "addon"


def blender_ext() -> Path:
    path = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core/bl_pkg/cli/blender_ext.py"
    assert path.is_file(), f"blender_ext.py not found at {path}"
    return path


def run(*args, **kwargs):
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True,
                          timeout=300, **kwargs)


def test_manifest_validates():
    res = run(blender_ext(), "validate", ADDON_DIR)
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    out = tmp_path_factory.mktemp("ext")
    res = run(blender_ext(), "build", "--source-dir", ADDON_DIR, "--output-dir", out)
    assert res.returncode == 0, res.stdout + res.stderr
    zips = list(out.glob("isac_twin-*.zip"))
    assert len(zips) == 1, res.stdout
    return zips[0]


def test_build_zip_contents(built_zip):
    names = zipfile.ZipFile(built_zip).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "exporter/__init__.py" in names
    # the contract the engine imports too, with its Apache-2.0 files
    for name in ("contract/__init__.py", "contract/schema.py", "contract/wire.py",
                 "contract/errors.py", "contract/writers/mitsuba_xml.py"):
        assert name in names, name
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


def test_install_zip_enable_and_run_operator(built_zip, tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    res = run(HERE / "_install_extension.py", built_zip, repo, env=env, cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["install"] == ["FINISHED"]
    assert out["enabled"] is True
    assert out["operator_module"].startswith("bl_ext.isac_test.isac_twin")
    assert out["add_room"] == ["FINISHED"]
    assert out["objects"] == ["Room_Ceiling", "Room_Floor", "Room_Wall_1", "Room_Wall_2",
                              "Room_Wall_3", "Room_Wall_4"]
    assert (repo / "isac_twin" / "blender_manifest.toml").is_file()
