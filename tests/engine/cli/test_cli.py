"""engine/cli/: info, run and fingerprints on real scene folders; bad input exits 2."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from isac_twin.cli import main
from isac_twin.scene.synthetic import two_ap_lab

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    return two_ap_lab(tmp_path_factory.mktemp("cli") / "lab",
                      tracer={"samples_per_src": 10000, "max_depth": 1})


def test_info_names_resources_and_links(lab, capsys):
    assert main(["info", str(lab)]) == 0
    out = capsys.readouterr().out
    assert "symbols [0, 7)" in out and "symbols [7, 14)" in out
    assert "link AP1 -> robot1" in out and "6 objects" in out


@pytest.mark.slow
def test_run_prints_a_line_per_step_and_timing(lab, capsys):
    assert main(["run", str(lab), "--steps", "3", "--timing"]) == 0
    out = capsys.readouterr().out
    assert out.count("step ") >= 3 and "AP2->robot1" in out and "Mbit/s" in out
    assert "steps/s" in out and "trace" in out
    # Paced far above what the lab can do: every step after the start-up step
    # (the twin's first) overruns, each with its cause.
    assert main(["run", str(lab), "--steps", "3", "--rate", "1000"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"paced at 1000 Hz: 3 steps in [\d.]+ s, 2 overruns \("
                     r"(agents|trace|phy|sense|estimate|control|caller) [12].*"
                     r"after a [\d.]+ s start-up", out), out


@pytest.mark.slow
def test_fingerprints_builds_then_reuses_the_cache(lab, tmp_path, capsys):
    args = ["fingerprints", str(lab), "--spacing", "1.0", "--cache-dir", str(tmp_path)]
    assert main(args) == 0
    first = capsys.readouterr().out
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and str(files[0]) in first
    mtime = files[0].stat().st_mtime_ns
    assert main(args) == 0
    assert files[0].stat().st_mtime_ns == mtime  # cached, not traced again


def test_bad_input_exits_2_with_the_culprit(lab, tmp_path, capsys):
    assert main(["run", str(lab), "--steps", "-1"]) == 2
    assert "--steps -1" in capsys.readouterr().err
    assert main(["run", str(lab), "--steps", "2", "--rate", "0"]) == 2
    assert "--rate 0.0: expected a positive rate" in capsys.readouterr().err
    assert main(["fingerprints", str(lab), "--spacing", "0"]) == 2
    bad = tmp_path / "twin.toml"
    bad.write_text((lab / "twin.toml").read_text().replace("rows = 2", "rows = 0"))
    assert main(["info", str(bad)]) == 2
    assert "array.rows: expected an integer >= 1" in capsys.readouterr().err
    assert main(["record", str(lab), "--share", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--share needs --connect" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_serve_token_from_file_or_environment(tmp_path, monkeypatch, capsys):
    """Issue 22: a token on the command line is visible in `ps`; a file or the
    environment keep it out of the process list. A bad token file exits 2 naming it."""
    monkeypatch.delenv("ISAC_TWIN_TOKEN", raising=False)
    empty = tmp_path / "empty.token"
    empty.write_text("\n")
    assert main(["serve", "--host", "0.0.0.0", "--port", "0", "--token-file", str(empty)]) == 2
    assert "empty.token: the token file is empty" in capsys.readouterr().err
    missing = tmp_path / "missing.token"
    assert main(["serve", "--port", "0", "--token-file", str(missing)]) == 2
    assert "missing.token: cannot read the token file" in capsys.readouterr().err
    assert main(["serve", "--host", "0.0.0.0", "--port", "0"]) == 2
    assert "ISAC_TWIN_TOKEN" in capsys.readouterr().err

    import argparse

    from isac_twin.cli import serve_token

    ns = argparse.Namespace(token=None, token_file=None)
    assert serve_token(ns) is None
    monkeypatch.setenv("ISAC_TWIN_TOKEN", "from-env")
    assert serve_token(ns) == "from-env"
    good = tmp_path / "good.token"
    good.write_text("from-file\nignored\n")
    assert serve_token(argparse.Namespace(token=None, token_file=good)) == "from-file"
    assert main(["serve", "--port", "0", "--asset-dir", str(missing)]) == 2
    assert "--asset-dir" in (err := capsys.readouterr().err) and "not a folder" in err


# --------------------------------------------------------------------------- fault suite (issue 22)
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
    import shutil

    name, damage, expect = _BAD_INPUTS[case]
    folder = tmp_path / "scene"
    shutil.copytree(box, folder)
    f = folder / name
    f.write_bytes(damage(f.read_bytes()))
    assert main(["info", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("isac-twin: error: ") and re.search(expect, err), err




@pytest.mark.slow
def test_localize_runs_the_case_study_on_an_l_room(tmp_path):
    """`isac-twin localize` on a non-lab room: its own polyline path from twin.toml, every
    output of the lab's demo, floor plan from its geometry; a bad --path exits 2."""
    import json

    from isac_twin.scene.synthetic import l_room

    f = l_room(tmp_path / "l", robot=(1.0, 1.0, 0.0),
               tracer={"samples_per_src": 2000, "max_depth": 1})
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "localize", str(f), "--out", str(out),
                        "--spacing", "0.6", "--steps", "3", "--table-points", "2",
                        "--snr", "20", "--cache-dir", str(tmp_path / "cache")],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "robot1 follows polyline of 4 waypoints" in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["paper_mode"]["path"]["waypoints"][1] == [3.5, 1.0]
    assert m["closed_loop"]["steps"] == 3
    # the default closed loop is the fused one; the headline (against the truth) first
    assert m["closed_loop"]["settings"]["method"] == "MCA-angles"
    assert m["closed_loop"]["settings"]["fusion"] == "ekf"
    assert list(m)[0] == "headline"
    for name in ("trajectories_paper.png", "errors_paper.png", "rates_paper.png",
                 "trajectories_closed_loop.png"):
        assert (out / name).stat().st_size > 10000, name
    assert (out / "table.md").read_text().count("| PDP |") == 2
    bad = subprocess.run([sys.executable, "-m", "isac_twin.cli", "localize", str(f), "--out",
                          str(out), "--path", '{kind = "circle", centre = [5, 4], radius = 0.5}'],
                         cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and "outside the room's footprint" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "isac_twin.cli", "localize", str(f), "--out",
                          str(out), "--closed-loop-fusion", "ukf"],
                         cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "--closed-loop-fusion: invalid choice: 'ukf'" in bad.stderr


@pytest.mark.slow
def test_cli_tools_on_the_bundled_l_office(tmp_path):
    """The second bundled room (L-shaped, 5.8 GHz, glass): info, trace and localize (coarse
    grid, a few steps) through the command line, on its own path from twin.toml."""
    import json

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
    import shutil

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


@pytest.mark.parametrize("cmd", ["grid", "fingerprints"])
def test_cluster_options_are_refused_in_one_line(lab, tmp_path, capsys, cmd):
    out = ["--out", str(tmp_path / "g.npz")] if cmd == "grid" else []
    for extra, why in ((["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"],
                        "--workers and --scheduler"),
                       (["--workers", "0"], "--workers 0: expected at least 1"),
                       (["--tile-size", "8"], "--tile-size: only with"),
                       (["--workers", "1", "--tile-size", "0"], "--tile-size 0")):
        assert main([cmd, str(lab), *out, *extra]) == 2
        err = capsys.readouterr().err
        assert why in err and len(err.strip().splitlines()) == 1, err
    if cmd == "grid":  # shoot-and-bounce per point is not tiled: refused before a cluster starts
        assert main([cmd, str(lab), *out, "--workers", "2", "--method", "sbr"]) == 2
        err = capsys.readouterr().err
        assert "chain reuse only" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "g.npz").exists()


@pytest.mark.slow
def test_fingerprints_on_two_workers_equal_the_single_process_database(lab, tmp_path):
    from isac_twin.localization.fingerprints import load_database

    base = ["fingerprints", str(lab), "--spacing", "0.5"]
    assert main([*base, "--cache-dir", str(tmp_path / "one")]) == 0
    assert main([*base, "--cache-dir", str(tmp_path / "two"), "--workers", "2"]) == 0
    (a,), (b,) = (list((tmp_path / d).iterdir()) for d in ("one", "two"))
    assert a.name == b.name  # same cache file name: scene hash, frequency, spacing
    da, db = load_database(a), load_database(b)
    assert db.meta["tracer"]["method"] == "chains"
    np.testing.assert_array_equal(db.arrays["num_paths"], da.arrays["num_paths"])
    for k, v in da.arrays.items():  # same paths, to float32 rounding (see tests/engine/scaleout)
        np.testing.assert_allclose(db.arrays[k], v, rtol=1e-5, equal_nan=True, err_msg=k)


@pytest.mark.slow
def test_run_radar_in_a_process_prints_the_synchronous_frames(capsys):
    """``--radar process``: the same radar lines as ``--radar sync``, each frame
    printed on the step that delivers it (step 0's on step 10; the last flushed)."""
    import isac_twin

    lines = {}
    for mode in ("sync", "process"):
        assert main(["run", str(isac_twin.bundled_scene_dir()), "--steps", "11", "--no-phy",
                     "--radar", mode]) == 0
        out = capsys.readouterr().out.splitlines()
        lines[mode] = [re.search(r"radar \(step \d+\).*", ln).group(0) for ln in out
                       if "radar (step" in ln]
        if mode == "process":
            assert "radar (step 0)" in next(ln for ln in out if ln.startswith("step   10"))
    assert [ln.split(")")[0] for ln in lines["sync"]] == ["radar (step 0", "radar (step 10"]
    assert lines["process"] == lines["sync"]


def test_run_and_record_refuse_radar_for_a_scene_without_one(lab, tmp_path, capsys):
    """Refused from the config, before a twin is built (and nothing recorded)."""
    assert main(["run", str(lab), "--steps", "1", "--radar", "process"]) == 2
    err = capsys.readouterr().err
    assert "--radar process" in err and "has no [[sensing]] radar" in err
    out = tmp_path / "run.mcap"
    assert main(["record", str(lab), "--steps", "1", "--out", str(out), "--radar", "sync"]) == 2
    assert "--radar sync" in capsys.readouterr().err and not out.exists()
