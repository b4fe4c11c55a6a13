"""isac_twin.cli.options: the options several commands share, refused in one line when
they do not fit."""

from __future__ import annotations

import pytest

from isac_twin.cli import main
from isac_twin.cli.options import input_errors
from isac_twin.errors import ConfigError, UsageError


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


def test_input_errors_types_plain_value_errors_only():
    with pytest.raises(UsageError, match=r"^--x: bad$"):
        with input_errors("--x: "):
            raise ValueError("bad")
    with pytest.raises(ConfigError, match=r"^twin.toml: bad$"):  # already typed: unchanged
        with input_errors("--x: "):
            raise ConfigError("twin.toml: bad")
    with pytest.raises(KeyError):  # not bad input: a bug
        with input_errors():
            raise KeyError("k")
