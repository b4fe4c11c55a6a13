"""isac_twin.cli.calibrate: what is refused before any fit (the fits themselves, driven
through the command, are in tests/engine/calibration/test_run.py)."""

from __future__ import annotations

import pytest

from isac_twin.cli import main
from isac_twin.cli.calibrate import parse_links
from isac_twin.errors import UsageError


def test_bad_input_is_refused_before_any_fit(lab, tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_text("not an mcap")
    out = tmp_path / "o"
    assert main(["calibrate", str(lab), "--measurements", str(junk), "--out", str(out)]) == 2
    assert f"{junk}: no 'csi' entry" in capsys.readouterr().err
    assert main(["calibrate", str(lab), "--measurements", str(tmp_path / "none.mcap"),
                 "--out", str(out)]) == 2
    assert f"--measurements {tmp_path / 'none.mcap'}: no such file" in capsys.readouterr().err
    assert main(["calibrate", str(lab), "--measurements", str(junk), "--links", "AP1",
                 "--out", str(out)]) == 2
    assert "--links: expected TX,RX[;TX,RX...], got 'AP1'" in capsys.readouterr().err
    assert not out.exists()


def test_links_option():
    assert parse_links("AP1,robot1; AP2 , robot1") == [("AP1", "robot1"), ("AP2", "robot1")]
    for bad in ("AP1", "AP1,", "AP1,robot1;", "a,b,c"):
        with pytest.raises(UsageError, match="--links"):
            parse_links(bad)
