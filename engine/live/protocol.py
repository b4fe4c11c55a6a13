"""The engine's side of the wire format: convert records to and from messages.

The format itself is ``addon/contract/wire.py``, the one definition the add-on and the
engine share (stdlib only), imported as ``isac_twin.contract.wire``; this module
re-exports it as :data:`wire`.
"""

from __future__ import annotations

import time

import numpy as np

from ..contract import wire
from ..twin.state import Command, Edit, StepResult

_ROUND = 4  # coordinates on the wire: 0.1 mm


def _vec(v, n=None) -> list[float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    return [round(float(x), 6) for x in (a if n is None else a[:n])]


def scene_message(scene) -> dict:
    """``scene`` message for a :class:`~isac_twin.scene.twin_scene.TwinScene`."""
    cfg = scene.config
    objects = [{"name": o.name, "material": o.material, "thickness": float(o.thickness),
                "bounds_min": _vec(o.bounds_min), "bounds_max": _vec(o.bounds_max)}
               for o in scene.objects.values()]
    devices = [{"name": d.name, "kind": d.kind, "role": d.role, "position": _vec(d.position),
                "orientation": _vec(d.orientation), "model": getattr(d, "model", None),
                "array": [int(d.array.rows), int(d.array.cols)]}
               for d in cfg.devices]
    return {"type": "scene", "name": cfg.scene.name, "content_hash": scene.content_hash(),
            "frequency_hz": float(cfg.scene.frequency_hz), "objects": objects,
            "devices": devices, "links": [[lk.tx, lk.rx] for lk in cfg.links]}


def state_message(res: StepResult) -> dict:
    """``state`` message: robot poses, velocities, odometry, estimates."""
    robots = []
    for name, r in res.robots.items():
        robots.append({
            "name": name, "pose": _vec(r.pose, 6), "velocity": _vec(r.velocity, 2),
            "odometry": None if r.odometry is None else _vec(r.odometry, 3),
            "estimate": None if r.estimate is None else _vec(r.estimate, 3)})
    msg = {"type": "state", "step": int(res.step), "time_s": float(res.time_s),
           "scene_hash": res.scene_hash, "robots": robots, "sent_at": time.time()}
    msg.update(sensing_fields(res))
    return msg


def sensing_fields(res: StepResult) -> dict:
    """``detections`` and ``tracks`` of a ``state`` message when the twin's radar
    ran this step (``res.sensing``), else nothing (the viewer keeps the last)."""
    s = getattr(res, "sensing", None)
    if s is None:
        return {}
    dets = [{"link": link, "snr_db": float(d.snr_db),
             "position": None if d.position is None else _vec(d.position, 3)}
            for link, ds in s.detections.items() for d in ds]
    tracks = [{"id": int(t.id), "position": _vec(t.position, 2),
               "velocity": _vec(t.velocity, 2)} for t in s.tracks]
    return {"detections": dets, "tracks": tracks}


def link_polylines(lp, max_paths: int) -> dict:
    """One link's ``paths`` entry: the ``max_paths`` strongest paths as polylines.

    Each polyline is tx array centre -> interaction vertices -> rx array centre
    (m), with the interaction codes and the path power ``|a|^2`` in dB.
    """
    n = lp.num_paths
    out = {"tx": lp.tx, "rx": lp.rx, "num_paths": int(n), "paths": []}
    if n == 0 or max_paths <= 0:
        return out
    p = lp.power
    order = np.argsort(-p, kind="stable")[:max_paths]
    with np.errstate(divide="ignore"):
        pdb = 10.0 * np.log10(np.maximum(p[order], 1e-30))
    tx = np.round(np.asarray(lp.tx_position, float), _ROUND).tolist()
    rx = np.round(np.asarray(lp.rx_position, float), _ROUND).tolist()
    verts = np.round(np.asarray(lp.vertices, float)[order], _ROUND)
    inter = np.asarray(lp.interactions)[order]
    counts = np.count_nonzero(inter != 0, axis=1)
    paths = out["paths"]
    for i in range(len(order)):
        k = int(counts[i])
        paths.append({"points": [tx, *verts[i, :k].tolist(), rx],
                      "types": [int(t) for t in inter[i, :k]],
                      "power_db": round(float(pdb[i]), 3),
                      "tau_s": float(lp.tau[order[i]])})
    return out


def link_rays(lp, max_paths: int) -> dict:
    """One link's ``rays`` entry (wire 1.3): the ``max_paths`` strongest paths of
    :func:`link_polylines`, packed (``wire.rays_link``): float32 vertices ``[P, 3]`` m,
    uint8 points per path and interaction codes, float32 power (dB) and delay (s)."""
    n = lp.num_paths
    order = np.argsort(-np.asarray(lp.power, float), kind="stable")[:max(max_paths, 0)]
    inter = np.asarray(lp.interactions)[order]
    c, depth = inter.shape
    counts = np.count_nonzero(inter != 0, axis=1)
    if depth + 2 > 255:
        raise ValueError(f"link {lp.tx}->{lp.rx}: {depth} interactions per path do not fit "
                         "the wire's uint8 point counts")
    full = np.empty((c, depth + 2, 3), np.float32)
    full[:, 0] = np.asarray(lp.tx_position, float)
    full[:, 1:depth + 1] = np.asarray(lp.vertices, float)[order]
    full[np.arange(c), counts + 1] = np.asarray(lp.rx_position, float)
    keep = np.arange(depth + 2)[None, :] < (counts + 2)[:, None]
    with np.errstate(divide="ignore"):
        pdb = 10.0 * np.log10(np.maximum(np.asarray(lp.power, float)[order], 1e-30))
    return wire.rays_link(
        lp.tx, lp.rx, int(n), sizes=(counts + 2).astype(np.uint8).tobytes(),
        points=full[keep].astype("<f4").tobytes(),
        types=inter[np.arange(depth)[None, :] < counts[:, None]].astype(np.uint8).tobytes(),
        power_db=pdb.astype("<f4").tobytes(),
        tau_s=np.asarray(lp.tau, float)[order].astype("<f4").tobytes())


def rays_message(res: StepResult, max_paths: int = wire.DEFAULT_MAX_PATHS_PER_LINK) -> dict:
    """``rays`` message (wire 1.3): the ``paths`` message's polylines packed per link."""
    links = [link_rays(ls.paths, max_paths) for ls in res.links.values()
             if ls.paths is not None]
    return {"type": "rays", "step": int(res.step), "links": links}


def paths_message(res: StepResult, max_paths: int = wire.DEFAULT_MAX_PATHS_PER_LINK) -> dict:
    """``paths`` message: per link the strongest ``max_paths`` polylines."""
    links = [link_polylines(ls.paths, max_paths) for ls in res.links.values()
             if ls.paths is not None]
    return {"type": "paths", "step": int(res.step), "links": links}


def metrics_message(res: StepResult) -> dict:
    """``metrics`` message: SNR (dB), rate (bit/s) and a path summary per link."""
    links = []
    for (tx, rx), ls in res.links.items():
        m = {"tx": tx, "rx": rx, "snr_db": wire.finite_or_none(ls.snr_db),
             "rate_bps": wire.finite_or_none(ls.rate_bps),
             "mcs_rate_bps": wire.finite_or_none(getattr(ls, "mcs_rate_bps", float("nan")))}
        if ls.paths is not None:
            s = ls.paths.summary()
            m.update(num_paths=int(s["num_paths"]), los=bool(s["los"]),
                     strongest_db=wire.finite_or_none(s["strongest_path_gain_db"]),
                     total_db=wire.finite_or_none(s["total_gain_db"]))
        links.append(m)
    return {"type": "metrics", "step": int(res.step), "links": links}


def step_summary(res: StepResult) -> dict:
    """A JSON line describing a step (the server's step log; tests compare against it)."""
    return {"step": int(res.step), "time_s": float(res.time_s), "scene_hash": res.scene_hash,
            "robots": {n: _vec(r.pose, 6) for n, r in res.robots.items()},
            "links": {f"{tx}->{rx}": {
                "num_paths": None if ls.paths is None else ls.paths.num_paths,
                "snr_db": wire.finite_or_none(ls.snr_db),
                "total_db": None if ls.paths is None else
                wire.finite_or_none(ls.paths.summary()["total_gain_db"])}
                for (tx, rx), ls in res.links.items()}}


def edit_from_message(msg: dict) -> Edit:
    """:class:`~isac_twin.twin.state.Edit` from a validated ``edit`` message.

    Raises:
        ValueError: ``mesh_ply`` is not base64.
    """
    def t(k):
        v = msg.get(k)
        return None if v is None else tuple(float(x) for x in v)
    return Edit(op=msg["op"], target=msg["target"], position=t("position"),
                orientation=t("orientation"), material=msg.get("material"),
                thickness=msg.get("thickness"), mesh_file=msg.get("mesh_file"),
                mesh_data=wire.edit_mesh(msg))


def command_from_message(msg: dict) -> Command:
    """:class:`~isac_twin.twin.state.Command` from a validated ``command`` message."""
    return Command(op=msg["op"], args=dict(msg.get("args") or {}))
