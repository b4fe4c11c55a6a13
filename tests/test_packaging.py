"""The package as a user installs it: a wheel in a fresh virtual environment, run
from a folder outside the repository."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out),
                        str(ROOT)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    (whl,) = out.glob("isac_twin-*.whl")
    return whl


def test_the_wheel_holds_one_package_with_its_data_and_licence(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"isac_twin"}, tops  # no top-level ``engine``, ``addon`` or ``blend_scenes``
    for need in ("isac_twin/__init__.py", "isac_twin/twin/twin.py", "isac_twin/cli/__main__.py",
                 "isac_twin/contract/wire.py", "isac_twin/contract/writers/mitsuba_xml.py",
                 "isac_twin/scenes/__init__.py", "isac_twin/scenes/aces_lab/scene/twin.toml",
                 "isac_twin/scenes/aces_lab/scene/scene.xml",
                 "isac_twin/scenes/l_office/scene/twin.toml"):
        assert need in names, need
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    # the GPL add-on's Blender glue and the rooms' bpy scripts and .blend files stay out
    assert not [n for n in names if n.endswith((".blend", "build_aces_lab.py", "live_view.py"))]
    z = zipfile.ZipFile(wheel)
    for n in names:
        if n.startswith("isac_twin/contract/") and n.endswith(".py"):
            assert "SPDX-License-Identifier: Apache-2.0" in z.read(n).decode(), n
    meta = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "License-Expression: Apache-2.0" in meta


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """A fresh venv with the wheel installed (``--no-deps``); the dependencies come from
    this environment's site-packages through a ``.pth`` line (a plain path entry: the
    editable install's finder there is not run), so nothing is downloaded again."""
    venv = tmp_path_factory.mktemp("venv") / "v"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                        str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                           "['purelib'])"], capture_output=True, text=True).stdout.strip()
    Path(site, "isac_twin_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return venv


def _run(venv: Path, cwd: Path, *args: str, timeout: float = 600):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DRJIT_LIBLLVM_PATH")}
    return subprocess.run([str(venv / "bin" / args[0]), *args[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_the_installed_package_is_the_wheel_not_the_checkout(installed, tmp_path):
    r = _run(installed, tmp_path, "python", "-c",
             "import isac_twin, isac_twin.contract.wire as w; "
             "print(isac_twin.__file__); print(w.__file__); print(isac_twin.bundled_scene_dir())")
    assert r.returncode == 0, r.stderr
    for line in r.stdout.split():
        assert line.startswith(str(installed)) and str(ROOT) not in line, line


@pytest.mark.parametrize("args", [
    ("info",),
    ("trace",),
    ("run", "--steps", "5"),
    ("radiomap", "--cell", "0.5", "--out", "rm"),
    ("calibrate", "--help"),
], ids=lambda a: a[0])
def test_commands_run_on_the_bundled_lab_outside_the_repository(installed, tmp_path, args):
    r = _run(installed, tmp_path, "isac-twin", *args)
    assert r.returncode == 0, f"isac-twin {' '.join(args)}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    if args[0] == "radiomap":
        assert (tmp_path / "rm" / "radiomap.png").is_file()
    if args[0] == "info":
        assert "aces_lab" in r.stdout or "ACES" in r.stdout
