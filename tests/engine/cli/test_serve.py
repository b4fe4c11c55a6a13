"""isac_twin.cli.serve: the live link's token, what is refused before the twin loads,
``--replay``, and how the process ends (SIGTERM, ``--linger``)."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from isac_twin.cli import main
from isac_twin.cli.serve import serve_token

from .conftest import ROOT


def test_serve_token_from_file_or_environment(tmp_path, monkeypatch, capsys):
    """A token on the command line is visible in `ps`; a file or the environment keep it
    out of the process list. A bad token file exits 2 naming it; a public address
    without a token is refused."""
    monkeypatch.delenv("ISAC_TWIN_TOKEN", raising=False)
    empty = tmp_path / "empty.token"
    empty.write_text("\n")
    assert main(["serve", "--host", "0.0.0.0", "--port", "0", "--token-file", str(empty)]) == 2
    assert "empty.token: the token file is empty" in capsys.readouterr().err
    missing = tmp_path / "missing.token"
    assert main(["serve", "--port", "0", "--token-file", str(missing)]) == 2
    assert "missing.token: cannot read the token file" in capsys.readouterr().err
    assert main(["serve", "--host", "0.0.0.0", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "without an auth token" in err and "ISAC_TWIN_TOKEN" in err

    ns = argparse.Namespace(token=None, token_file=None)
    assert serve_token(ns) is None
    monkeypatch.setenv("ISAC_TWIN_TOKEN", "from-env")
    assert serve_token(ns) == "from-env"
    good = tmp_path / "good.token"
    good.write_text("from-file\nignored\n")
    assert serve_token(argparse.Namespace(token=None, token_file=good)) == "from-file"
    assert main(["serve", "--port", "0", "--asset-dir", str(missing)]) == 2
    assert "--asset-dir" in (err := capsys.readouterr().err) and "not a folder" in err


def _line_source(t: float, dt: float):
    """A robot driven along y = 1.5 at 0.5 m/s from x = 1 (no simulation would do this)."""
    from isac_twin.robots.kinematics import KinematicState

    return KinematicState(pose=np.array([1.0 + 0.5 * t, 1.5, 0.0, 0.0, 0.0, 0.0]), v=0.5,
                          w=0.0, t=t)


def _serve(args, tmp_path):
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, "-m", "isac_twin.cli", "serve", *args, "--port", "0",
                             "--port-file", str(port_file), "--rate", "0", "--paused"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)
    end = time.monotonic() + 90
    while not port_file.exists():
        if proc.poll() is not None or time.monotonic() > end:
            out = proc.communicate(timeout=10)[0].decode()
            raise AssertionError(f"serve did not listen: {out}")
        time.sleep(0.1)
    return proc, int(port_file.read_text())


@pytest.mark.slow
def test_serve_replays_a_recording(tmp_path, box_scene_dir, raw_viewer):
    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    twin = Twin.from_scene(box_scene_dir, dt=0.2)
    twin.set_state_source("robot1", _line_source)
    run = tmp_path / "run.mcap"
    record_twin(twin, 4, run)
    proc, port = _serve([str(box_scene_dir), "--replay", str(run)], tmp_path)
    try:
        v = raw_viewer(("127.0.0.1", port))
        v.hello()
        v.until(lambda m: m["type"] == "scene")
        for k in range(3):
            v.send({"type": "command", "op": "step"})
            st = v.until(lambda m: m["type"] == "state" and m["step"] == k)
            pose = st["robots"][0]["pose"]
            # the recording's dt (0.2 s, not serve's default) and its trajectory
            assert st["time_s"] == pytest.approx(0.2 * (k + 1))
            assert pose[:2] == pytest.approx([1.0 + 0.5 * st["time_s"], 1.5], abs=1e-3)
    finally:
        proc.terminate()
        proc.wait(20)


def test_serve_refuses_a_bad_recording(tmp_path, box_scene_dir):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file")
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "serve", str(box_scene_dir),
                        "--replay", str(bad), "--port", "0"], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert r.returncode == 2
    assert f"--replay {bad}" in r.stderr and "ground_truth" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.slow
def test_serve_ends_on_sigterm_and_after_its_linger(tmp_path, box_scene_dir):
    """Paused until SIGTERM: a clean stop (exit 0, the closing line). With --steps and
    --linger: it ends by itself that long after the last step."""
    proc, _ = _serve([str(box_scene_dir)], tmp_path)
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate(timeout=30)[0].decode()
    assert proc.returncode == 0 and "isac-twin serve: stopped after 0 steps" in out, out
    # nobody signals this one: it ends by itself after lingering (else run() times out)
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "serve", str(box_scene_dir),
                        "--port", "0", "--rate", "0", "--steps", "2", "--linger", "0.5"],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "isac-twin serve: stopped after 2 steps" in r.stdout
