"""Ray tracing: the tracer interface and its backends.

``from isac_twin.raytrace import make_tracer, device_poses``::

    scene = load_scene(folder)
    tracer = make_tracer(scene.config)        # [tracer].backend: "sionna" | "grid"
    links = tracer(scene, device_poses(scene.config))   # {(tx, rx): LinkPaths}

Backends are imported lazily so that reading paths or grid files never
needs Sionna. See ``docs/tracers.md``.
"""

from __future__ import annotations

from ..errors import TruncationError
from .base import (
    DevicePose,
    Link,
    LinkPaths,
    Tracer,
    device_poses,
    sionna_orientation,
    validate_poses,
)

__all__ = ["DevicePose", "Link", "LinkPaths", "Tracer", "TruncationError", "device_poses",
           "sionna_orientation", "validate_poses", "make_tracer"]


def make_tracer(config) -> Tracer:
    """The backend ``config.tracer.backend`` names (``config`` is a ``TwinConfig``).

    ``"grid"`` reads ``tracer.grid_file`` (relative to ``twin.toml``).
    """
    t = config.tracer
    if t.backend == "sionna":
        from .sionna import SionnaTracer

        return SionnaTracer(t)
    if t.backend == "grid":
        from .grid_backend import GridTracer

        return GridTracer(config.folder / t.grid_file)
    raise ValueError(f"{config.path}: tracer.backend: unknown backend {t.backend!r}")
