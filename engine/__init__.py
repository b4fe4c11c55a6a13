"""ISAC Twin engine: a headless digital twin for indoor integrated sensing,
communications and robotics (paper: Andrei et al., "A Digital Twinning
Platform for Integrated Sensing, Communications and Robotics").

Public API (kept short on purpose)::

    from engine import load_config, load_scene, bundled_scene_dir
"""

from engine._llvm import configure_llvm as _configure_llvm

_configure_llvm()  # before anything imports mitsuba

from engine.config import ConfigError, TwinConfig, load_config  # noqa: E402
from engine.paths import bundled_scene_dir  # noqa: E402

__all__ = ["ConfigError", "TwinConfig", "load_config", "bundled_scene_dir"]
__version__ = "0.1.0"
