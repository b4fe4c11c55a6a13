"""isac_twin.cli.localize: fingerprints and localize (the case study)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from isac_twin.cli import main
from isac_twin.cli.localize import parse_path_option
from isac_twin.errors import UsageError

from .conftest import ROOT


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


def test_fingerprints_refuse_a_bad_spacing(lab, tmp_path, capsys):
    assert main(["fingerprints", str(lab), "--spacing", "0", "--cache-dir", str(tmp_path)]) == 2
    assert "--spacing 0.0: expected a positive size in m" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_path_option_reads_toml_or_json():
    toml = parse_path_option('{kind = "circle", centre = [4, 3], radius = 1.5}')
    assert toml == parse_path_option('{"kind": "circle", "centre": [4, 3], "radius": 1.5}')
    assert toml == {"kind": "circle", "centre": [4, 3], "radius": 1.5}
    with pytest.raises(UsageError, match=r"--path: expected a TOML inline table or a JSON"):
        parse_path_option("circle(4, 3)")


@pytest.mark.slow
def test_localize_runs_the_case_study_on_an_l_room(tmp_path):
    """`isac-twin localize` on a non-lab room: its own polyline path from twin.toml, every
    output of the lab's demo, floor plan from its geometry; a bad --path exits 2."""
    from isac_twin.scene.synthetic import l_room

    f = l_room(tmp_path / "l", robot=(1.0, 1.0, 0.0),
               tracer={"samples_per_src": 2000, "max_depth": 1})
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "localize", str(f), "--out",
                        str(out), "--spacing", "0.6", "--steps", "3", "--table-points", "2",
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
