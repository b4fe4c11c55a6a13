"""engine/cli.py: info, run and fingerprints on real scene folders; bad input exits 2."""

import pytest

from engine.cli import main
from engine.synthetic import two_ap_lab


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
    assert main(["record", str(lab), "--share", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--share needs --connect" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()
