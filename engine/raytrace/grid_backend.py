"""Grid backend: serve paths from a precomputed floor grid (``isac-twin grid``).

:class:`GridTracer` implements the :class:`~isac_twin.raytrace.base.Tracer`
protocol for static transmitters (those the grid was traced against) and
receivers that move on the floor at the grid's height. A receiver gets the
paths of the **nearest grid point** (no interpolation: the set of paths
changes between neighbouring points and their phases are not interpolable);
the returned :class:`~isac_twin.raytrace.base.LinkPaths` carries the grid
point as ``rx_position`` and ``extra = {"grid_index", "snap_distance_m"}``.
The position error is at most ``spacing / sqrt(2)``.

Doppler is computed from the poses' velocities as Sionna does for a static
scene: ``nu = (r_t . v_tx + r_r . v_rx) / lambda`` with ``r_t``, ``r_r`` the
unit departure / arrival directions.

A link from a moving device to a grid transmitter (uplink) is served by
reciprocity (:meth:`~isac_twin.raytrace.base.LinkPaths.reversed`).

Errors (``ValueError`` naming the device): a position outside the stored
grid, at another height (more than ``height_tolerance``), at a grid point
that is not in free space, a transmitter whose pose differs from the one the
grid was traced with, a receiver that is tilted (roll or pitch), or a scene
whose content hash differs from the grid's.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from .antenna_patterns import apply_elements
from .base import (
    SPEED_OF_LIGHT,
    DevicePose,
    Link,
    LinkPaths,
    empty_link,
    resolve_links,
    validate_poses,
)
from .grid import PathGrid, load_grid


def _r_hat(theta, phi) -> np.ndarray:
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


class GridTracer:
    """Tracer backend serving a :class:`~isac_twin.raytrace.grid.PathGrid`.

    Args:
        grid: a grid file path or a loaded :class:`PathGrid`.
        height_tolerance: allowed |z - grid height| of a receiver, m.
        position_tolerance: allowed transmitter displacement from the traced pose, m.
        check_scene: refuse scenes whose content hash differs from the grid's.
    """

    def __init__(self, grid: PathGrid | str | Path, *, height_tolerance: float = 0.01,
                 position_tolerance: float = 1e-3, check_scene: bool = True):
        self.grid = grid if isinstance(grid, PathGrid) else load_grid(grid)
        self.height_tolerance = float(height_tolerance)
        self.position_tolerance = float(position_tolerance)
        self.check_scene = check_scene

    def _check_tx(self, name: str, pose: DevicePose) -> int:
        g = self.grid
        s = g.tx_names.index(name)
        moved = np.linalg.norm(np.asarray(pose.position) - g.tx_positions[s])
        if moved > self.position_tolerance:
            raise ValueError(
                f"device {name!r}: transmitter moved {moved:.4f} m from where the grid was "
                f"traced ({g.tx_positions[s].tolist()}); re-run `isac-twin grid`")
        turned = np.abs(np.asarray(pose.orientation) - g.tx_orientations[s]).max()
        if turned > 1e-6:
            raise ValueError(f"device {name!r}: orientation {list(pose.orientation)} differs "
                             f"from the traced {g.tx_orientations[s].tolist()}")
        if np.any(np.asarray(pose.velocity) != 0):
            raise ValueError(f"device {name!r}: grid transmitters are static, got velocity "
                             f"{list(pose.velocity)}")
        return s

    def _locate(self, name: str, pose: DevicePose) -> tuple[int, float]:
        g = self.grid
        z = pose.position[2]
        if abs(z - g.height) > self.height_tolerance:
            raise ValueError(f"device {name!r}: height z={z:.4f} m differs from the grid height "
                             f"{g.height:.4f} m (tolerance {self.height_tolerance} m)")
        roll, pitch = pose.orientation[:2]
        if abs(roll) > 1e-6 or abs(pitch) > 1e-6:
            raise ValueError(f"device {name!r}: the grid was traced with upright receivers, "
                             f"got roll={roll}, pitch={pitch} rad")
        try:
            i, dist = g.nearest(pose.position)
        except ValueError as exc:
            raise ValueError(f"device {name!r}: {exc}") from None
        if not g.free[i]:
            raise ValueError(f"device {name!r}: position {list(pose.position)} is at grid point "
                             f"{g.points[i].tolist()}, which is not in free space (inside an "
                             "object or outside the room)")
        return i, dist

    def _link(self, tx: str, rx: str, pt: DevicePose, pr: DevicePose) -> LinkPaths:
        g = self.grid
        s = self._check_tx(tx, pt)
        i, dist = self._locate(rx, pr)
        f = float(g.meta["frequency_hz"])
        rx_pose = DevicePose(position=tuple(g.points[i]), orientation=pr.orientation,
                             velocity=pr.velocity)
        d = g.paths(i, s)
        if d["tau"].size == 0:
            lp = empty_link(tx, rx, pt, rx_pose, f, g.arrays["interactions"].shape[-1])
        else:
            th_t, ph_t = d["theta_t"].astype(float), d["phi_t"].astype(float)
            th_r, ph_r = d["theta_r"].astype(float), d["phi_r"].astype(float)
            lam = SPEED_OF_LIGHT / f
            doppler = (_r_hat(th_t, ph_t) @ np.asarray(pt.velocity)
                       + _r_hat(th_r, ph_r) @ np.asarray(pr.velocity)) / lam
            lp = LinkPaths(
                tx=tx, rx=rx, tx_position=np.asarray(g.tx_positions[s], float),
                rx_position=np.asarray(g.points[i], float),
                tx_orientation=np.asarray(pt.orientation, float),
                rx_orientation=np.asarray(pr.orientation, float), frequency_hz=f,
                a=d["a"].astype(np.complex128), tau=d["tau"].astype(float), doppler=doppler,
                theta_t=th_t, phi_t=ph_t, theta_r=th_r, phi_r=ph_r,
                vertices=d["vertices"].astype(float),
                interactions=d["interactions"].astype(np.int32))
        lp.extra.update(grid_index=i, snap_distance_m=dist)
        return lp

    def __call__(self, scene, poses: Mapping[str, DevicePose],
                 links: Iterable[Link] | None = None) -> dict[Link, LinkPaths]:
        g = self.grid
        if self.check_scene and scene.content_hash() != g.meta["scene_hash"]:
            raise ValueError(f"{g.path or 'grid'}: traced for another scene (content hash "
                             f"{g.meta['scene_hash'][:12]}, scene {scene.content_hash()[:12]})")
        if abs(scene.config.scene.frequency_hz - g.meta["frequency_hz"]) > 1e-6:
            raise ValueError(f"{g.path or 'grid'}: traced at {g.meta['frequency_hz']} Hz, "
                             f"scene is at {scene.config.scene.frequency_hz} Hz")
        links = resolve_links(scene.config, links)
        validate_poses(scene, poses, dict.fromkeys(n for lk in links for n in lk))
        out = {}
        for tx, rx in links:
            if tx in g.tx_names and rx not in g.tx_names:
                out[(tx, rx)] = self._link(tx, rx, poses[tx], poses[rx])
            elif rx in g.tx_names and tx not in g.tx_names:
                out[(tx, rx)] = self._link(rx, tx, poses[rx], poses[tx]).reversed()
            else:
                raise ValueError(f"link {tx}->{rx}: the grid serves links between one of its "
                                 f"transmitters ({', '.join(g.tx_names)}) and a moving device")
        return apply_elements(scene.config, out)
