"""ISAC Twin: a digital twin for indoor integrated sensing, communications and robotics.

After Andrei et al., "A Digital Twinning Platform for Integrated Sensing,
Communications and Robotics". The public API is short on purpose::

    from isac_twin import Twin, load_scene, bundled_scene_dir

    twin = Twin(load_scene(bundled_scene_dir("aces_lab")))
    for result in twin.run(100):
        print(result.time_s, {k: l.rate_bps for k, l in result.links.items()})

Names are imported on first use (PEP 562), so ``import isac_twin`` -- and the
stdlib-only ``isac_twin.contract`` -- stay light; Sionna RT and Dr.Jit load when a
scene is traced. Importing the package points Dr.Jit at a usable LLVM first
(:mod:`isac_twin.utils.llvm`).
"""

from __future__ import annotations

import importlib

if __name__ != "isac_twin":  # e.g. ``import engine`` from the repository root
    raise ImportError(f"the engine/ folder is the package 'isac_twin': import isac_twin, not "
                      f"{__name__} (`python3 build.py setup` installs it into .venv)")

from .utils.llvm import configure_llvm as _configure_llvm  # noqa: E402

_configure_llvm()  # before anything imports mitsuba

__version__ = "0.1.0"

#: public name -> the module that defines it
_EXPORTS = {
    "Twin": ".twin", "StepResult": ".twin", "RobotState": ".twin", "LinkState": ".twin",
    "Edit": ".twin", "Command": ".twin",
    "load_scene": ".scene", "TwinScene": ".scene", "load_config": ".scene",
    "TwinConfig": ".scene", "bundled_scene_dir": ".scene", "bundled_scenes": ".scene",
    "make_tracer": ".raytrace", "device_poses": ".raytrace", "LinkPaths": ".raytrace",
    "NetworkPHY": ".phy",
    "IsacTwinError": ".errors", "ConfigError": ".errors", "MeshError": ".errors",
    "PathError": ".errors", "CalibrationError": ".errors", "DeviceError": ".errors",
    "WireError": ".errors",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'isac_twin' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
