"""Where the project's bundled data lives."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def bundled_scene_dir(name: str = "aces_lab") -> Path:
    """The exported scene folder of a bundled room (the engine's default).

    Args:
        name: room name, a folder under ``blend_scenes/``.
    """
    return REPO_ROOT / "blend_scenes" / name / "scene"
