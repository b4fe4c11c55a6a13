"""isac_twin.cli.run: run, record, replay and recover."""

from __future__ import annotations

import re
from collections import Counter

import pytest

from isac_twin.cli import main
from isac_twin.transport.record import LINKS_TOPIC, PATHS_TOPIC, read_messages, read_metadata

from .conftest import LAB


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


def test_run_command_prints_the_frame_still_out_at_the_end(capsys):
    """`isac-twin run` waits for the radar frame the sensing worker still computes
    when the steps end and prints it with the step it sensed."""
    assert main(["run", str(LAB), "--steps", "2", "--no-phy"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split()[1] for ln in lines[:2]] == ["0", "1"]
    assert "radar" not in lines[0] and "radar" not in lines[1]  # not delivered yet
    assert lines[2].startswith("radar (step 0) ") and lines[2].endswith(" tracks")


@pytest.mark.slow
def test_run_radar_in_a_process_prints_the_synchronous_frames(capsys):
    """``--radar process``: the same radar lines as ``--radar sync``, each frame
    printed on the step that delivers it (step 0's on step 10; the last flushed)."""
    lines = {}
    for mode in ("sync", "process"):
        assert main(["run", str(LAB), "--steps", "11", "--no-phy", "--radar", mode]) == 0
        out = capsys.readouterr().out.splitlines()
        lines[mode] = [re.search(r"radar \(step \d+\).*", ln).group(0) for ln in out
                       if "radar (step" in ln]
        if mode == "process":
            assert "radar (step 0)" in next(ln for ln in out if ln.startswith("step   10"))
    assert [ln.split(")")[0] for ln in lines["sync"]] == ["radar (step 0", "radar (step 10"]
    assert lines["process"] == lines["sync"]


def test_bad_options_exit_2_with_the_culprit(lab, tmp_path, capsys):
    assert main(["run", str(lab), "--steps", "-1"]) == 2
    assert "--steps -1" in capsys.readouterr().err
    assert main(["run", str(lab), "--steps", "2", "--rate", "0"]) == 2
    assert "--rate 0.0: expected a positive rate" in capsys.readouterr().err
    assert main(["record", str(lab), "--share", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--share needs --connect" in capsys.readouterr().err
    assert main(["record", str(lab), "--steps", "1", "--out", str(tmp_path / "x.mcap"),
                 "--csi-snr", "nan"]) == 2
    assert "--csi-snr: CsiRecording.snr_db: expected a finite number" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_run_and_record_refuse_radar_for_a_scene_without_one(lab, tmp_path, capsys):
    """Refused from the config, before a twin is built (and nothing recorded)."""
    assert main(["run", str(lab), "--steps", "1", "--radar", "process"]) == 2
    err = capsys.readouterr().err
    assert "--radar process" in err and "has no [[sensing]] radar" in err
    out = tmp_path / "run.mcap"
    assert main(["record", str(lab), "--steps", "1", "--out", str(out), "--radar", "sync"]) == 2
    assert "--radar sync" in capsys.readouterr().err and not out.exists()


def test_recover_refuses_what_is_not_a_recording(tmp_path, capsys):
    text = tmp_path / "text.mcap"
    text.write_text("not an mcap")
    assert main(["recover", str(text)]) == 2
    err = capsys.readouterr().err
    assert f"{text}: not an MCAP file" in err and len(err.splitlines()) == 1, err


@pytest.mark.slow
def test_record_then_replay(tmp_path, capsys):
    """`isac-twin record` on the bundled scene (Sionna tracing), then `isac-twin replay`."""
    out = tmp_path / "run.mcap"
    assert main(["record", "--steps", "2", "--out", str(out)]) == 0
    assert "recorded" in capsys.readouterr().out
    topics = Counter(m.topic for m in read_messages(out))
    assert topics[LINKS_TOPIC] >= 2 and topics[PATHS_TOPIC] >= 2
    assert topics["/robot1/ground_truth"] == 2
    assert read_metadata(out)["scene"].endswith("scene")
    # REP-105 frames and a compact file: the lab's CSI decimated, zstd chunks
    assert topics["/tf"] == 2 and topics["/tf_static"] == 1 and topics["/clock"] == 2
    assert out.stat().st_size / 2 <= 100_000
    csi = next(m.decode() for m in read_messages(out, ["/robot1/csi"]))
    assert csi.h.shape[0] == 1 and csi.h.shape[1] == 1024 // 16
    assert main(["replay", str(out), "--speed", "0"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("step")]
    assert len(lines) == 2 and "AP1->robot1" in lines[0]
    assert main(["replay", str(out), "--bus-only", "--speed", "0"]) == 0
    assert f"replayed {sum(topics.values())} messages" in capsys.readouterr().out
