"""The scene: a validated scene folder (``twin.toml``, ``scene.xml``, meshes), the room
as a floor plan, the Sionna scene it loads into, the bundled rooms and synthetic test
rooms written from code.

Modules, one concept each: :mod:`.config` (``twin.toml`` -> :class:`TwinConfig`),
:mod:`.meshes` (PLY reading), :mod:`.room` (shell vs furniture, free space),
:mod:`.twin_scene` (:class:`TwinScene`, :func:`load_scene`), :mod:`.bundled` (the
bundled rooms), :mod:`.synthetic` (analytic rooms for tests and benchmarks).
"""

from .bundled import bundled_scene_dir, bundled_scenes
from .config import TwinConfig, load_config
from .twin_scene import TwinScene, load_scene

__all__ = ["TwinConfig", "TwinScene", "bundled_scene_dir", "bundled_scenes", "load_config",
           "load_scene"]
