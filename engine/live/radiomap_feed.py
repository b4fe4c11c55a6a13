"""Radio maps on the live link: build ``radiomap`` messages and keep viewers' maps current.

:class:`RadioMapFeed` is handed to :class:`~isac_twin.live.server.LiveServer` as
its ``on_step`` hook (the loop thread, the only thread that touches the
twin's Sionna scene). After a step it recomputes the map when the scene's
content hash or the access points' poses changed (the twin applies viewers'
edits right before a step) and publishes it; :meth:`RadioMapFeed.prime`
computes the first map before the server starts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from ..radiomap.radio_map import DEFAULT_CELL_M, RadioMap, compute_radio_map
from ..utils.geometry import DevicePose
from .protocol import wire

log = logging.getLogger(__name__)

#: Width of the colour scale of RSS layers, dB below the strongest cell.
RSS_SCALE_DB = 60.0


def _values(a: np.ndarray) -> list:
    """Row-major ``[ny * nx]`` list, 0.1 dB resolution, None where not finite."""
    flat = np.round(np.asarray(a, float).reshape(-1), 1)
    return [float(x) if math.isfinite(x) else None for x in flat]


def _scale(a: np.ndarray, width: float | None) -> tuple[float, float]:
    f = a[np.isfinite(a)]
    if not f.size:
        return 0.0, 1.0
    hi = float(np.ceil(f.max()))
    lo = hi - width if width is not None else float(np.floor(f.min()))
    return lo, max(hi, lo + 1.0)


def radiomap_message(rm: RadioMap, step: int | None = None) -> dict:
    """The ``radiomap`` message for ``rm``: one RSS layer (dBm) per access point on a shared
    scale of :data:`RSS_SCALE_DB`, ``best`` (best server's RSS, dBm, same scale) and ``sinr``
    (best server, full reuse, dB)."""
    lo, hi = _scale(rm.rss_dbm, RSS_SCALE_DB)
    layers = [{"name": n, "unit": "dBm", "vmin": lo, "vmax": hi, "values": _values(rm.rss_dbm[i])}
              for i, n in enumerate(rm.tx_names)]
    layers.append({"name": "best", "unit": "dBm", "vmin": lo, "vmax": hi,
                   "values": _values(rm.best_rss_dbm)})
    slo, shi = _scale(rm.sinr_db, None)
    layers.append({"name": "sinr", "unit": "dB", "vmin": slo, "vmax": shi,
                   "values": _values(rm.sinr_db)})
    msg = {"type": "radiomap", "scene_hash": str(rm.meta.get("scene_hash", "")),
           "height": rm.height, "origin": [float(x) for x in rm.origin],
           "cell_size": rm.cell_size, "shape": list(rm.shape), "layers": layers,
           "tx": [{"name": n, "position": [float(x) for x in p]}
                  for n, p in zip(rm.tx_names, rm.tx_positions)]}
    if step is not None:
        msg["step"] = int(step)
    return msg


class RadioMapFeed:
    """Recompute the twin's radio map when its room changed; publish it.

    Args:
        twin: the served twin (its ``scene``; ``ap_poses`` when it has them).
        publish: where messages go (``LiveServer.publish``; set after construction).
        cell_size: cell edge, m; samples_per_tx: rays per access point.
        compute: the map function (``compute_radio_map``'s signature).
    """

    def __init__(self, twin, publish: Callable[[dict], None] | None = None, *,
                 cell_size: float = DEFAULT_CELL_M, samples_per_tx: int = 200_000,
                 compute: Callable[..., RadioMap] = compute_radio_map):
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise ValueError(f"radio map cell size: expected a positive number of metres, "
                             f"got {cell_size!r}")
        self.twin = twin
        self.publish = publish
        self.cell_size = float(cell_size)
        self.samples_per_tx = int(samples_per_tx)
        self.compute = compute
        self.key: tuple | None = None
        self.last: RadioMap | None = None
        self.last_message: dict | None = None
        #: maps computed so far
        self.computed = 0

    def _poses(self) -> dict[str, DevicePose]:
        """Access-point poses the twin holds now (``Twin.ap_poses``: name -> (position,
        orientation)); empty for twins without them (the config's poses apply)."""
        raw = getattr(self.twin, "ap_poses", None) or {}
        return {n: DevicePose(position=tuple(map(float, p)), orientation=tuple(map(float, o)))
                for n, (p, o) in raw.items()}

    def _key(self) -> tuple:
        return (self.twin.scene.content_hash(),
                tuple(sorted((n, p.position, p.orientation) for n, p in self._poses().items())))

    def prime(self) -> dict:
        """Compute the map now (call before the server's threads start); return the message."""
        return self._update(None, force=True)

    def __call__(self, res) -> None:
        """The server's ``on_step`` hook: recompute and publish when the room changed."""
        try:
            msg = self._update(getattr(res, "step", None))
        except Exception as exc:  # noqa: BLE001 - a failed map must not stop the twin
            log.exception("radio map update failed")
            if self.publish is not None:
                self.publish(wire.error("radiomap", f"radio map not updated: {exc}"))
            return
        if msg is not None and self.publish is not None:
            try:
                self.publish(msg)
            except wire.WireError as exc:
                log.error("radio map not sent: %s (use a coarser --radiomap cell)", exc)

    def _update(self, step, force: bool = False) -> dict | None:
        key = self._key()
        if not force and key == self.key:
            return None
        self.last = self.compute(self.twin.scene, cell_size=self.cell_size,
                                 samples_per_tx=self.samples_per_tx, poses=self._poses())
        self.key = key
        self.computed += 1
        self.last_message = radiomap_message(self.last, step)
        log.info("radio map %d x %d recomputed (%s)", *self.last.shape[::-1],
                 "first" if self.computed == 1 else "room changed")
        return self.last_message
