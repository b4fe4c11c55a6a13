"""The bundled rooms: exported scene folders that ship with the package.

They live in the repository's ``blend_scenes/<room>/scene/`` and are installed as
package data of ``isac_twin.scenes`` (``pyproject.toml`` maps that package to
``blend_scenes/``), so a source checkout, an editable install and an installed
wheel find them the same way, through :mod:`importlib.resources`.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..errors import ConfigError

__all__ = ["DEFAULT_SCENE", "bundled_scene_dir", "bundled_scenes", "scenes_root"]

#: The room every command uses when given no scene.
DEFAULT_SCENE = "aces_lab"


def scenes_root() -> Path:
    """The folder of the bundled rooms: ``blend_scenes/`` in a checkout (with each
    room's ``.blend`` and build script), ``isac_twin/scenes/`` in an installed wheel
    (the scene folders only)."""
    return Path(str(resources.files("isac_twin.scenes")))


def bundled_scenes() -> list[str]:
    """Names of the bundled rooms (folders with an exported ``scene/twin.toml``)."""
    return sorted(p.name for p in scenes_root().iterdir() if (p / "scene" / "twin.toml").is_file())


def bundled_scene_dir(name: str = DEFAULT_SCENE) -> Path:
    """The exported scene folder of a bundled room.

    Args:
        name: room name (:func:`bundled_scenes`), e.g. ``"aces_lab"``, ``"l_office"``.

    Raises:
        ConfigError: no bundled room of that name; the message lists them.
    """
    folder = scenes_root() / name / "scene"
    if not (folder / "twin.toml").is_file():
        raise ConfigError(f"no bundled scene {name!r}: the bundled rooms are "
                          f"{', '.join(bundled_scenes())}")
    return folder
