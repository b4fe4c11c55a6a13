"""``isac-twin serve --replay RUN.mcap``: a viewer sees a recorded run re-traced (the robots
placed along the recording, at its time step), what ``render_live.py --replay`` renders."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest


def _line_source(t: float, dt: float):
    """A robot driven along y = 1.5 at 0.5 m/s from x = 1 (no simulation would do this)."""
    from isac_twin.robots.kinematics import KinematicState

    return KinematicState(pose=np.array([1.0 + 0.5 * t, 1.5, 0.0, 0.0, 0.0, 0.0]), v=0.5,
                          w=0.0, t=t)


def _serve(args, tmp_path):
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, "-m", "isac_twin.cli", "serve", *args, "--port", "0",
                             "--port-file", str(port_file), "--rate", "0", "--paused"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
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
                       timeout=120)
    assert r.returncode == 2
    assert f"--replay {bad}" in r.stderr and "ground_truth" in r.stderr
