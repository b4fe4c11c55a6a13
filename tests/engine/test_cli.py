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

    from engine.cli import serve_token

    ns = argparse.Namespace(token=None, token_file=None)
    assert serve_token(ns) is None
    monkeypatch.setenv("ISAC_TWIN_TOKEN", "from-env")
    assert serve_token(ns) == "from-env"
    good = tmp_path / "good.token"
    good.write_text("from-file\nignored\n")
    assert serve_token(argparse.Namespace(token=None, token_file=good)) == "from-file"
    assert main(["serve", "--port", "0", "--asset-dir", str(missing)]) == 2
    assert "--asset-dir" in (err := capsys.readouterr().err) and "not a folder" in err
