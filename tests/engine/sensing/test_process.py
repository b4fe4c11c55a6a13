"""The radar in a child process (``isac_twin.sensing.process``): the frames of the
synchronous radar, on the worker's schedule, from a replica of the twin's scene
that follows its edits; errors of the child raised on the twin's thread."""

import pickle
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest

from isac_twin.sensing.estimator import SensingJob
from isac_twin.sensing.process import SensingProcess

ROOT = Path(__file__).resolve().parents[3]
LAB = ROOT / "blend_scenes" / "aces_lab" / "scene"

# A script without a ``__main__`` guard, as users write them: multiprocessing's
# spawn ran it again in the child, which built a second twin and failed.
_SCRIPT = textwrap.dedent("""
    import gc, pickle, sys
    from isac_twin.twin.state import Edit
    from isac_twin.twin.twin import Twin
    sync = sys.argv[2] == "sync"
    tw = Twin.from_scene({lab!r}, dt=0.05, phy=False, sync_sensing=sync,
                         sensing_process=not sync)
    delivered = []
    for k in range(21):
        if k == 5:  # edits while the frame of step 0 is out, seen by frame 10
            tw.apply_edit(Edit(op="move", target="Chair_1", position=[1.0, 1.0, 0.45]))
            for wall in ("Lab_Floor", "Lab_Ceiling"):  # echoes off them change power
                tw.apply_edit(Edit(op="material", target=wall, material="metal"))
        r = tw.step()
        if r.sensing is not None:
            delivered.append((r.step, r.sensing.step))
    tw.flush_sensing()

    def frames():
        return [(f.step, f.time_s, {{k: [(d.path_length_m, d.doppler_hz, d.azimuth_rad,
                 d.snr_db, None if d.position is None else d.position.tolist()) for d in v]
                 for k, v in f.detections.items()}}, [(t.id, t.x.tolist(), t.P.tolist())
                 for t in f.tracks]) for f in tw.radar.history]

    before = frames()
    tw.step()  # a frame out, dropped by the reset
    tw.reset()  # the room keeps its edits; a new radar
    assert tw.radar.history == []
    for k in range(11):
        tw.step()
    tw.flush_sensing()
    pickle.dump((delivered, before, frames()), open(sys.argv[1], "wb"))
    tw.close()
""")


def _frames(tmp_path, mode):
    script = tmp_path / "radar_frames.py"
    script.write_text(_SCRIPT.format(lab=str(LAB)))
    out = tmp_path / f"{mode}.pkl"
    r = subprocess.run([sys.executable, str(script), str(out), mode], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return pickle.loads(out.read_bytes())


@pytest.mark.slow
def test_process_frames_equal_the_synchronous_radar_through_edits_and_a_reset(tmp_path):
    sync_delivered, sync_frames, sync_after = _frames(tmp_path, "sync")
    delivered, frames, after = _frames(tmp_path, "process")
    assert sync_delivered == [(0, 0), (10, 10), (20, 20)]
    assert delivered == [(10, 0), (20, 10)]  # the worker's schedule; 20 flushed
    assert [f[0] for f in frames] == [0, 10, 20]
    assert sum(len(v) for f in sync_frames for v in f[2].values()) > 0
    assert frames == sync_frames  # bit-identical detections and tracks
    # after a reset (the child's radar starts again too): frames of steps 0 and 10
    assert [f[0] for f in after] == [0, 10] and after == sync_after


def _job():
    from isac_twin.phy.ofdm import ResourceGrid

    return SensingJob(step=0, time_s=0.05, dt=0.05, links=[], poses={}, truth={},
                      grid=ResourceGrid(64, 78125.0, 14, 8), contains=None)


def test_a_child_that_cannot_start_says_why(tmp_path):
    missing = tmp_path / "gone" / "twin.toml"
    scene = SimpleNamespace(config=SimpleNamespace(path=missing), edits=[],
                            content_hash=lambda: "0" * 64)
    p = SensingProcess(scene, [], seed=0, latency=1)
    p.submit(_job(), 0)
    with pytest.raises(RuntimeError, match=r"could not start.*gone"):
        p.collect()
    p.close()
    p.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        p.submit(_job(), 1)
    with pytest.raises(ValueError, match="latency"):
        SensingProcess(scene, [], seed=0, latency=0)
    with pytest.raises(ValueError, match="nice"):
        SensingProcess(scene, [], seed=0, latency=1, nice=25)


@pytest.mark.slow
def test_a_scene_changed_behind_the_edits_is_refused_not_sensed():
    """The replica follows the edit methods; a change made around them (here an
    object's material set directly) would make the child sense another room:
    the frame is refused, on the twin's thread, naming the cause."""
    from isac_twin import load_scene
    from isac_twin.sensing.config import parse_sensing

    scene = load_scene(LAB, load_sionna=False)
    links = parse_sensing(scene.config)
    p = SensingProcess(scene, links, seed=0, latency=1)
    scene.objects["Chair_1"] = replace(scene.objects["Chair_1"], material="metal")
    p.submit(replace(_job(), links=links), 0)
    with pytest.raises(RuntimeError, match="changed other than by TwinScene's edit methods"):
        p.collect()
    p.close()


def test_the_child_ending_is_an_error_on_collect():
    scene = SimpleNamespace(config=SimpleNamespace(path=LAB / "twin.toml"), edits=[],
                            content_hash=lambda: "0" * 64)
    p = SensingProcess(scene, [], seed=0, latency=1)
    p._proc.kill()
    p._proc.wait()
    with pytest.raises(RuntimeError, match="child ended"):
        p.submit(_job(), 0)
        p.collect()
    p.close()
