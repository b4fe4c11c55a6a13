"""engine/cli.py: info, run and fingerprints on real scene folders; bad input exits 2."""

import subprocess
import sys
from pathlib import Path

import pytest

from engine.cli import main
from engine.synthetic import two_ap_lab

ROOT = Path(__file__).resolve().parents[2]


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
    assert main(["fingerprints", str(lab), "--spacing", "0"]) == 2
    bad = tmp_path / "twin.toml"
    bad.write_text((lab / "twin.toml").read_text().replace("rows = 2", "rows = 0"))
    assert main(["info", str(bad)]) == 2
    assert "array.rows: expected an integer >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_localize_runs_the_case_study_on_an_l_room(tmp_path):
    """`isac-twin localize` on a non-lab room: its own polyline path from twin.toml, every
    output of the lab's demo, floor plan from its geometry; a bad --path exits 2."""
    import json

    from engine.synthetic import l_room

    f = l_room(tmp_path / "l", robot=(1.0, 1.0, 0.0),
               tracer={"samples_per_src": 2000, "max_depth": 1})
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "engine.cli", "localize", str(f), "--out", str(out),
                        "--spacing", "0.6", "--steps", "3", "--table-points", "2",
                        "--snr", "20", "--cache-dir", str(tmp_path / "cache")],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "robot1 follows polyline of 4 waypoints" in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["paper_mode"]["path"]["waypoints"][1] == [3.5, 1.0]
    assert m["closed_loop"]["steps"] == 3
    for name in ("trajectories_paper.png", "errors_paper.png", "rates_paper.png",
                 "trajectories_closed_loop.png"):
        assert (out / name).stat().st_size > 10000, name
    assert (out / "table.md").read_text().count("| PDP |") == 2
    bad = subprocess.run([sys.executable, "-m", "engine.cli", "localize", str(f), "--out",
                          str(out), "--path", '{kind = "circle", centre = [5, 4], radius = 0.5}'],
                         cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and "outside the room's footprint" in bad.stderr


@pytest.mark.slow
def test_cli_tools_on_the_bundled_l_office(tmp_path):
    """The second bundled room (L-shaped, 5.8 GHz, glass): info, trace and localize (coarse
    grid, a few steps) through the command line, on its own path from twin.toml."""
    import json

    folder = ROOT / "blend_scenes" / "l_office" / "scene"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "engine.cli", *args], cwd=ROOT,
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
