"""isac_twin.cli.scene: info, trace, grid and radiomap on real scene folders; a damaged
input file ends in one line and exit status 2."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from isac_twin.cli import main
from isac_twin.radiomap.radio_map import load_radio_map
from isac_twin.raytrace.grid import load_grid
from isac_twin.scene.synthetic import furnished_room

from .conftest import ROOT


def test_info_names_resources_and_links(lab, capsys):
    assert main(["info", str(lab)]) == 0
    out = capsys.readouterr().out
    assert "symbols [0, 7)" in out and "symbols [7, 14)" in out
    assert "link AP1 -> robot1" in out and "6 objects" in out


def test_trace_json_and_npz(tmp_path, capsys):
    folder = furnished_room(tmp_path / "room")
    assert main(["trace", str(folder), "--out", str(tmp_path / "t.json")]) == 0
    out = capsys.readouterr().out
    assert "AP1 -> robot1" in out and "LOS delay ns" in out
    doc = json.loads((tmp_path / "t.json").read_text())
    assert [r["rx"] for r in doc["links"]] == ["robot1", "robot1"]
    assert all(r["los"] and r["num_paths"] > 1 for r in doc["links"])
    assert main(["trace", str(folder), "--out", str(tmp_path / "t.npz")]) == 0
    z = np.load(tmp_path / "t.npz")
    assert z["AP1->robot1/tau"].shape == z["AP1->robot1/a"].shape
    assert main(["trace", str(folder), "--out", str(tmp_path / "t.txt")]) == 2


def test_grid(tmp_path, capsys):
    folder = furnished_room(tmp_path / "room")
    out = tmp_path / "g.npz"
    assert main(["grid", str(folder), "--spacing", "0.7", "--out", str(out)]) == 0
    assert "points in free space" in capsys.readouterr().out
    g = load_grid(out)
    assert g.spacing == 0.7 and g.tx_names == ["AP1", "AP2"]
    assert g.meta["tracer"]["method"] == "chains"
    assert main(["grid", str(folder), "--spacing", "-1", "--out", str(out)]) == 2
    assert main(["grid", str(folder), "--spacing", "0", "--out", str(tmp_path / "bad.npz")]) == 2
    assert "spacing" in capsys.readouterr().err
    assert not (tmp_path / "bad.npz").exists()
    assert main(["grid", str(folder), "--spacing", "0.7", "--method", "sbr",
                 "--out", str(tmp_path / "s.npz")]) == 0
    assert load_grid(tmp_path / "s.npz").meta["tracer"]["method"] == "sbr"


@pytest.mark.slow
def test_radiomap_writes_png_and_npz(lab, tmp_path, capsys):
    assert main(["radiomap", str(lab), "--out", str(tmp_path), "--cell", "0.5",
                 "--samples", "20000"]) == 0
    out = capsys.readouterr().out
    assert "AP1: RSS" in out and "AP2: RSS" in out
    rm = load_radio_map(tmp_path / "radiomap.npz")
    assert rm.tx_names == ["AP1", "AP2"] and rm.cell_size == 0.5
    png = (tmp_path / "radiomap.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert main(["radiomap", str(lab), "--out", str(tmp_path), "--tx", "robot9"]) == 2
    assert "unknown device 'robot9'" in capsys.readouterr().err


# --------------------------------------------------------------------------- fault suite
# Each case damaged one input file of a valid scene folder; each used to end in a
# traceback, a runaway allocation or a silently wrong result.

def _sub(old, new):
    def f(blob):
        assert old in blob
        return blob.replace(old, new, 1)
    return f


_BAD_INPUTS = {
    "non-UTF-8 twin.toml": ("twin.toml", _sub(b'name = "', b'name = "\xff\xfe'),
                            r"twin\.toml: not UTF-8 text \(byte \d+"),
    "samples_per_src 1e12": ("twin.toml", lambda b: b + b"\n[tracer]\nsamples_per_src = "
                             b"1000000000000\n", r"tracer\.samples_per_src: .*<= 100000000"),
    "max_depth 100000": ("twin.toml", lambda b: b + b"\n[tracer]\nmax_depth = 100000\n",
                         r"tracer\.max_depth: expected an integer <= 32"),
    "subcarrier spacing 1e308": ("twin.toml", _sub(b"subcarrier_spacing_hz = 78125.0",
                                                   b"subcarrier_spacing_hz = 1e308"),
                                 r"ofdm\.subcarrier_spacing_hz: expected a number <= 1e\+07"),
    "num_subcarriers 1e9": ("twin.toml", _sub(b"num_subcarriers = 1024",
                                              b"num_subcarriers = 1000000000"),
                            r"ofdm\.num_subcarriers: expected an integer <= 65536"),
    "num_symbols 100000": ("twin.toml", _sub(b"num_symbols = 14", b"num_symbols = 100000"),
                           r"ofdm\.num_symbols: expected an integer <= 4096"),
    "array rows 1e12": ("twin.toml", _sub(b"rows = 2", b"rows = 1000000000000"),
                        r"array\.rows: expected an integer <= 256"),
    "array rows 2^70": ("twin.toml", _sub(b"rows = 2", b"rows = 1180591620717411303424"),
                        r"array\.rows: expected an integer <= 256"),
    "power_dbm 1e308": ("twin.toml", _sub(b"power_dbm = 20.0", b"power_dbm = 1e308"),
                        r"power_dbm: expected a number <= 100"),
    "thickness inf": ("scene.xml", _sub(b'name="thickness" value="0.2"',
                                        b'name="thickness" value="inf"'),
                      r"scene\.xml: bsdf .*thickness must be in \(0, 10\] m, got inf"),
    "<transform> in scene.xml": ("scene.xml", _sub(b'<boolean name="face_normals" value="true"/>',
                                                   b'<transform name="to_world"><translate '
                                                   b'x="5"/></transform>'),
                                 r"scene\.xml: shape '\w+': a <transform> is not supported"),
    "unknown XML property": ("scene.xml", _sub(b'<boolean name="face_normals" value="true"/>',
                                               b'<boolean name="bogus" value="true"/>'),
                             r"scene\.xml: shape '\w+': <boolean name='bogus'> is not supported"),
    "PLY element vertex abc": ("meshes/floor.ply", lambda b: re.sub(
        rb"element vertex \d+", b"element vertex abc", b),
        r"floor\.ply: header line 'element vertex abc': expected 'element NAME COUNT'"),
    "PLY trailing bytes": ("meshes/floor.ply", lambda b: b + b"junk",
                           r"floor\.ply: 4 bytes after the last element"),
    "robot path leaving the room": ("twin.toml", _sub(
        b"antenna_offset = [0.0, 0.0, 0.25]\n", b"antenna_offset = [0.0, 0.0, 0.25]\n"
        b'path = { kind = "circle", centre = [3.0, 2.0], radius = 5.0 }\n'),
        r"twin\.toml: devices\[1\] \(robot1\)\.path: (circle .* leaves the room|the circle "
        r".* is not in free space: .*outside the room's footprint)"),
    "PLY 1e12 vertices": ("meshes/floor.ply", lambda b: re.sub(
        rb"element vertex \d+", b"element vertex 1000000000000", b), r"floor\.ply: "),
}


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    from isac_twin.scene.synthetic import box_room

    return box_room(tmp_path_factory.mktemp("faults") / "box")


@pytest.mark.parametrize("case", list(_BAD_INPUTS))
def test_bad_input_files_exit_2_with_one_line(box, tmp_path, capsys, case):
    name, damage, expect = _BAD_INPUTS[case]
    folder = tmp_path / "scene"
    shutil.copytree(box, folder)
    f = folder / name
    f.write_bytes(damage(f.read_bytes()))
    assert main(["info", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("isac-twin: error: ") and re.search(expect, err), err


def _loop(path):
    """Make ``path`` one end of a symbolic-link loop."""
    path.unlink(missing_ok=True)
    other = path.with_name(path.name + ".loop")
    path.symlink_to(other)
    other.symlink_to(path)


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)


def _dir(path):
    path.unlink(missing_ok=True)
    path.mkdir()


@pytest.mark.parametrize("name, make, expect", [
    ("scene.xml", _dir, r"scene\.xml: not a regular file \(a directory\)"),
    ("scene.xml", _fifo, r"scene\.xml: not a regular file \(a FIFO\)"),
    ("scene.xml", _loop, r"twin\.toml: scene\.file: a symbolic-link loop"),
    ("twin.toml", _fifo, r"twin\.toml: not a regular file \(a FIFO\)"),
    ("twin.toml", _loop, r"twin\.toml: a symbolic-link loop"),
    ("meshes/floor.ply", _loop,
     r"scene\.xml: object 'floor': mesh path 'meshes/floor\.ply': a symbolic-link loop"),
    ("meshes/floor.ply", _fifo, r"floor\.ply: not a regular file"),
])
@pytest.mark.parametrize("cmd", ["info", "trace"])
def test_scene_files_that_are_not_regular_files_exit_2_at_once(box, tmp_path, capsys, name,
                                                               make, expect, cmd):
    """A scene file that is a directory, a FIFO or a symbolic-link loop is refused in
    one line with exit 2, without blocking (before: a traceback and exit 1, and a FIFO
    as scene.file hung ``info`` and ``trace``)."""
    import shutil
    import threading

    folder = tmp_path / "scene"
    shutil.copytree(box, folder)
    make(folder / name)
    rc = []
    t = threading.Thread(target=lambda: rc.append(main([cmd, str(folder)])), daemon=True)
    t.start()
    t.join(60)
    if t.is_alive():  # blocked on the FIFO: give it a writer so the thread ends
        with open(folder / name, "wb"):
            pass
        t.join(10)
        pytest.fail(f"isac-twin {cmd} blocked on {name}")
    assert rc == [2]
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("isac-twin: error: ") and re.search(expect, err), err


@pytest.mark.slow
def test_cli_tools_on_the_bundled_l_office(tmp_path):
    """The second bundled room (L-shaped, 5.8 GHz, glass): info, trace and localize (coarse
    grid, a few steps) through the command line, on its own path from twin.toml."""
    folder = ROOT / "blend_scenes" / "l_office" / "scene"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "isac_twin.cli", *args], cwd=ROOT,
                              capture_output=True, text=True)

    r = cli("info", str(folder))
    assert r.returncode == 0, r.stderr
    assert "5.8 GHz" in r.stdout and "glass (0.02 m): 1 -- Glass_Partition" in r.stdout
    r = cli("trace", str(folder), "--out", str(tmp_path / "t.json"))
    assert r.returncode == 0, r.stderr
    links = json.loads((tmp_path / "t.json").read_text())["links"]
    assert len(links) == 2 and all(lk["los"] for lk in links)
    # the same room with a lighter tracer (2 bounces, 10^4 rays): the database in ~10 s
    light = tmp_path / "light"
    shutil.copytree(folder, light)
    with open(light / "twin.toml", "a") as f:
        f.write("\n[tracer]\nmax_depth = 2\nsamples_per_src = 10000\n")
    out = tmp_path / "loc"
    r = cli("localize", str(light), "--out", str(out), "--spacing", "0.8", "--steps", "3",
            "--table-points", "2", "--snr", "20", "--cache-dir", str(tmp_path / "cache"))
    assert r.returncode == 0, r.stderr[-3000:]
    assert "robot1 follows polyline of 6 waypoints" in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["paper_mode"]["path"]["closed"] is True
    assert m["database"]["frequency_hz"] == 5.8e9
    assert (out / "trajectories_closed_loop.png").stat().st_size > 10000
