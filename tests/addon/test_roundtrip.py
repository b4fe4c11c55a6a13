"""Round trip: the bundled ACES lab, built and exported by the add-on, in plain Sionna RT.

Only ``sionna.rt`` reads the exported folder here (no engine code). bpy 5.0.1
and Mitsuba 3.9 / Dr.Jit 1.5 load and trace fine in one process (checked), so
no subprocess is needed; tests/conftest.py sets DRJIT_LIBLLVM_PATH first.
"""

from __future__ import annotations

import json
import math
import runpy
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = [pytest.mark.blender, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
LAB_DIR = ROOT / "blend_scenes" / "aces_lab"
SPEED_OF_LIGHT = 299_792_458.0


def load_build_script():
    module = SimpleNamespace(**runpy.run_path(str(LAB_DIR / "build_aces_lab.py")))
    return module


@pytest.fixture(scope="module")
def lab(addon_module, reset_scene, tmp_path_factory):
    """(exported folder, {name: (bbox_min, bbox_max)} measured in Blender, {name: (type, thickness)})."""
    from addon.exporter import export_scene, geometry_objects, safe_name

    build = load_build_script()
    scene = build.build(bpy.context.scene)
    folder = tmp_path_factory.mktemp("aces_lab")
    export_scene(scene, folder)
    dg = bpy.context.evaluated_depsgraph_get()
    boxes, mats = {}, {}
    for obj in geometry_objects(scene):
        ev = obj.evaluated_get(dg)
        pts = [ev.matrix_world @ v.co for v in ev.data.vertices]
        boxes[safe_name(obj.name)] = (
            [min(p[i] for p in pts) for i in range(3)], [max(p[i] for p in pts) for i in range(3)])
        mats[safe_name(obj.name)] = (obj.isac.itu_material, obj.isac.thickness)
    yield folder, boxes, mats, build
    reset_scene()


@pytest.fixture(scope="module")
def sionna_scene(lab):
    rt = pytest.importorskip("sionna.rt")
    return rt.load_scene(str(lab[0] / "scene.xml"), merge_shapes=False)


def test_lab_layout(lab):
    folder, boxes, mats, build = lab
    lo = [min(b[0][i] for b in boxes.values()) for i in range(3)]
    hi = [max(b[1][i] for b in boxes.values()) for i in range(3)]
    assert lo == pytest.approx([-0.2, -0.2, -0.2], abs=1e-5)
    assert hi == pytest.approx([8.2, 6.2, 3.2], abs=1e-5)
    assert mats["Lab_Floor"][0] == "concrete" and mats["Lab_Ceiling"][0] == "ceiling_board"
    assert {mats[f"Lab_Wall_{i}"][0] for i in range(1, 5)} == {"concrete"}
    assert mats["Lab_Window"][0] == "glass"
    kinds = {n: m[0] for n, m in mats.items()}
    assert {kinds[n] for n in kinds if n.startswith(("Table", "Chair"))} == {"wood"}
    assert {kinds[n] for n in kinds if n.startswith(("Rack", "SwitchBox"))} == {"metal"}
    # the robot's circle (centre (4, 3), r = 1.5 m + 0.35 m) is free of furniture
    for name, (bmin, bmax) in boxes.items():
        if name.startswith("Lab_"):
            continue
        dx = max(bmin[0] - 4.0, 0.0, 4.0 - bmax[0])
        dy = max(bmin[1] - 3.0, 0.0, 3.0 - bmax[1])
        assert math.hypot(dx, dy) >= 1.85, name


def test_committed_scene_folder_is_current(lab):
    """blend_scenes/aces_lab/scene equals a fresh export (USD aside: not byte-deterministic)."""
    folder = lab[0]
    committed = LAB_DIR / "scene"
    fresh = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    stored = sorted(p.relative_to(committed).as_posix() for p in committed.rglob("*")
                    if p.is_file())
    assert fresh == stored
    for rel in fresh:
        if not rel.endswith(".usdc"):
            assert (folder / rel).read_bytes() == (committed / rel).read_bytes(), rel


def test_objects_materials_and_bboxes_in_sionna(lab, sionna_scene):
    _, boxes, mats, _ = lab
    assert sorted(sionna_scene.objects) == sorted(boxes)
    worst = 0.0
    for name, (bmin, bmax) in boxes.items():
        obj = sionna_scene.objects[name]
        mat = obj.radio_material
        assert mat.itu_type == mats[name][0], name
        assert float(mat.thickness[0]) == pytest.approx(mats[name][1], abs=1e-7), name
        bb = obj.mi_mesh.bbox()
        for i in range(3):
            worst = max(worst, abs(bb.min[i] - bmin[i]), abs(bb.max[i] - bmax[i]))
    assert worst < 1e-4
    print(f"max |bbox Sionna - bbox Blender| = {worst:.3g} m over {len(boxes)} objects")


def test_los_delay_is_distance_over_c(sionna_scene):
    rt = pytest.importorskip("sionna.rt")
    import numpy as np

    scene = sionna_scene
    scene.frequency = 2.4e9
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    tx, rx = (2.5, 3.0, 1.5), (5.5, 3.4, 1.2)  # across the robot's free circle
    scene.add(rt.Transmitter("los_tx", position=list(tx)))
    scene.add(rt.Receiver("los_rx", position=list(rx)))
    try:
        paths = rt.PathSolver()(scene, max_depth=1, los=True, specular_reflection=True,
                                diffuse_reflection=False, refraction=False, seed=1)
        tau = np.asarray(paths.tau.numpy()).reshape(-1)
        valid = np.asarray(paths.valid.numpy()).reshape(-1)
        taus = np.sort(tau[valid])
        distance = math.dist(tx, rx)
        assert taus[0] == pytest.approx(distance / SPEED_OF_LIGHT, rel=1e-6)
        assert len(taus) >= 6  # LOS plus floor, ceiling and wall reflections
        expected = distance / SPEED_OF_LIGHT
        print(f"LOS tau = {taus[0]:.9e} s, d/c = {expected:.9e} s, "
              f"relative error {abs(taus[0] - expected) / expected:.2e}, {len(taus)} paths")
    finally:
        scene.remove("los_tx")
        scene.remove("los_rx")


REEXPORT = r"""
import hashlib, json, sys
sys.path.insert(0, sys.argv[1])
import bpy
import addon
addon.register()
bpy.ops.wm.open_mainfile(filepath=sys.argv[2])
from addon.exporter import export_scene
report = export_scene(bpy.context.scene, sys.argv[3])
print(json.dumps(report.files))
"""


def test_saved_blend_reexports_identically(tmp_path):
    """aces_lab.blend keeps every radio setting: exporting it again gives the committed folder."""
    res = subprocess.run([sys.executable, "-c", REEXPORT, str(ROOT), str(LAB_DIR / "aces_lab.blend"),
                          str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    committed = LAB_DIR / "scene"
    files = json.loads(res.stdout.strip().splitlines()[-1])
    assert files == sorted(p.relative_to(committed).as_posix() for p in committed.rglob("*")
                           if p.is_file())
    for rel in files:
        if not rel.endswith(".usdc"):  # USD is not byte-deterministic (see test_export)
            assert (tmp_path / rel).read_bytes() == (committed / rel).read_bytes(), rel
