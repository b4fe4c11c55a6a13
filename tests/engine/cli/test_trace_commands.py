"""`isac-twin trace` and `isac-twin grid` on a small synthetic room."""

from __future__ import annotations

import json

import numpy as np

from isac_twin.cli import main
from isac_twin.raytrace.grid import load_grid
from isac_twin.scene.synthetic import furnished_room


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
