"""addon/scripts/render_live.py under headless bpy: its options and the MP4 of a frame
sequence (Blender's own FFmpeg, read back as a movie clip)."""

from __future__ import annotations

import runpy
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

SCRIPT = Path(__file__).resolve().parents[2] / "addon" / "scripts" / "render_live.py"


@pytest.fixture(scope="module")
def render_live():
    mod = SimpleNamespace(**runpy.run_path(str(SCRIPT)))
    return mod


def test_options(render_live, tmp_path, capsys):
    a = render_live.parse_args(["--mp4", str(tmp_path / "r.mp4")])
    assert a.sequence and not a.closeup and a.fps == 10          # --mp4: frames, no close-ups
    a = render_live.parse_args(["--engine", "BLENDER_WORKBENCH"])
    assert not a.sequence and a.closeup and a.engine == "BLENDER_WORKBENCH"
    with pytest.raises(SystemExit):
        render_live.parse_args(["--replay", str(tmp_path / "missing.mcap")])
    assert f"--replay {tmp_path / 'missing.mcap'}: no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        render_live.parse_args(["--mp4", "x.mp4", "--fps", "0"])
    assert "--fps: expected >= 1, got 0" in capsys.readouterr().err


def test_frames_to_mp4(render_live, tmp_path):
    frames = []
    for k in range(4):
        img = bpy.data.images.new(f"frame{k}", 64, 48)
        img.pixels.foreach_set([k / 4, 0.3, 1 - k / 4, 1.0] * 64 * 48)
        img.filepath_raw = str(tmp_path / f"frame_{k + 1:04d}.png")
        img.file_format = "PNG"
        img.save()
        bpy.data.images.remove(img)
        frames.append(tmp_path / f"frame_{k + 1:04d}.png")
    scenes = set(bpy.data.scenes.keys())
    out = render_live.frames_to_mp4(frames, tmp_path / "movie" / "run.mp4", fps=5)
    assert out == tmp_path / "movie" / "run.mp4" and out.stat().st_size > 0
    assert set(bpy.data.scenes.keys()) == scenes                     # scratch scene removed
    clip = bpy.data.movieclips.load(str(out))
    assert clip.frame_duration == 4 and tuple(clip.size) == (64, 48)
    bpy.data.movieclips.remove(clip)
    with pytest.raises(ValueError, match="no frames"):
        render_live.frames_to_mp4([], tmp_path / "none.mp4")
