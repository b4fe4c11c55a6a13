"""A minimal real twin for the live link: robots drive straight lines, Sionna traces each step.

Stands in for ``engine.twin.Twin`` where the full twin is not available (and
in tests that need a deterministic twin): it implements the
:class:`~engine.live.server.LiveTwin` protocol with real ray tracing on the
real scene, but no PHY, sensors or localization. Each robot drives along its
heading at ``speed`` and turns back when it comes within ``margin`` of the
room's bounding box. SNR is the link budget from the traced paths:
``P_tx + 10 log10(sum |a|^2) - N0 B`` with thermal noise at 290 K and a
7 dB noise figure; the rate is Shannon's ``B log2(1 + snr)``.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path

import numpy as np

from engine.raytrace.base import DevicePose, device_poses, sionna_orientation
from engine.state import Command, Edit, LinkState, RobotState, StepResult

log = logging.getLogger(__name__)

NOISE_FIGURE_DB = 7.0


class LineTwin:
    """Robots on straight lines through a real Sionna scene.

    Args:
        scene: a loaded :class:`~engine.scene.TwinScene`.
        speed: forward speed of every robot, m/s.
        dt: step duration, s.
        margin: distance kept from the room's bounding box, m.
        seed: unused (the Sionna tracer is deterministic with the config's seed).
    """

    def __init__(self, scene, *, speed: float = 0.2, dt: float = 0.1, margin: float = 0.5,
                 seed: int = 0):
        from engine.raytrace.sionna import SionnaTracer

        self.scene = scene
        self.speed, self.dt, self.margin = float(speed), float(dt), float(margin)
        self.tracer = SionnaTracer(scene.config.tracer)
        self._devices = {d.name: d for d in scene.config.devices}
        self._edits: list[str] = []
        self.reset()

    @classmethod
    def from_scene(cls, path: str | Path, seed: int = 0, **kw) -> "LineTwin":
        from engine.scene import load_scene

        return cls(load_scene(path), seed=seed, **kw)

    def reset(self) -> None:
        """Robots back to their configured poses, time to 0 (scene edits are kept)."""
        self.k = 0
        self._pose = {n: np.array([*d.position, *d.orientation], float)
                      for n, d in self._devices.items() if d.kind == "robot"}
        self._v = {n: self.speed for n in self._pose}
        self._w = {n: 0.0 for n in self._pose}
        self._fixed = {n: DevicePose(tuple(d.position), tuple(d.orientation))
                       for n, d in self._devices.items() if d.kind != "robot"}

    def _advance(self, name: str) -> None:
        p, v, w = self._pose[name], self._v[name], self._w[name]
        lo = self.scene.bounds_min[:2] + self.margin
        hi = self.scene.bounds_max[:2] - self.margin
        nxt = p[:2] + v * self.dt * np.array([math.cos(p[5]), math.sin(p[5])])
        if np.any(nxt < lo) or np.any(nxt > hi):
            p[5] = math.atan2(math.sin(p[5] + math.pi), math.cos(p[5] + math.pi))
            nxt = np.clip(p[:2] + v * self.dt * np.array([math.cos(p[5]), math.sin(p[5])]),
                          lo, hi)
        p[:2] = nxt
        p[5] = math.atan2(math.sin(p[5] + w * self.dt), math.cos(p[5] + w * self.dt))

    def poses(self) -> dict[str, DevicePose]:
        """Array-centre poses of all devices now."""
        cfg = self.scene.config
        out = dict(device_poses(cfg))
        out.update(self._fixed)
        for n, p in self._pose.items():
            yaw = p[5]
            off = np.asarray(self._devices[n].antenna_offset, float)
            c, s = math.cos(yaw), math.sin(yaw)
            centre = p[:3] + np.array([c * off[0] - s * off[1], s * off[0] + c * off[1], off[2]])
            vel = self._v[n] * np.array([c, s, 0.0])
            out[n] = DevicePose(tuple(centre), (0.0, 0.0, float(yaw)), tuple(vel))
        return out

    def step(self) -> StepResult:
        """Advance the robots by ``dt`` and trace every link."""
        import time

        t0 = time.perf_counter()
        for n in self._pose:
            self._advance(n)
        t1 = time.perf_counter()
        paths = self.tracer(self.scene, self.poses())
        t2 = time.perf_counter()
        ofdm = self.scene.config.ofdm
        bw = ofdm.num_subcarriers * ofdm.subcarrier_spacing_hz
        noise_dbm = -174.0 + 10 * math.log10(bw) + NOISE_FIGURE_DB
        links = {}
        for key, lp in paths.items():
            g = float(lp.power.sum())
            snr_db = (self._devices[key[0]].power_dbm + 10 * math.log10(g) - noise_dbm
                      if g > 0 else float("nan"))
            rate = bw * math.log2(1 + 10 ** (snr_db / 10)) if g > 0 else 0.0
            links[key] = LinkState(tx=key[0], rx=key[1], paths=lp, snr_db=snr_db, rate_bps=rate)
        self.k += 1
        robots = {n: RobotState(name=n, pose=p.copy(), velocity=np.array([self._v[n], self._w[n]]),
                                odometry=np.array([p[0], p[1], p[5]]), estimate=None)
                  for n, p in self._pose.items()}
        return StepResult(step=self.k - 1, time_s=self.k * self.dt, robots=robots, links=links,
                          timings_s={"robots": t1 - t0, "trace": t2 - t1},
                          scene_hash=self.scene_hash())

    def scene_hash(self) -> str:
        """The scene folder's content hash, extended by the edits applied since loading."""
        if not self._edits:
            return self.scene.content_hash()
        h = hashlib.sha256(self.scene.content_hash().encode())
        for e in self._edits:
            h.update(e.encode())
        return h.hexdigest()

    def apply_edit(self, edit: Edit) -> None:
        """Apply ``move`` (objects and devices) and ``material`` edits.

        ``move`` of an object: rotate it to ``orientation`` (relative to the
        loaded geometry, about its bounding-box centre) and put its
        bounding-box centre at ``position`` (Sionna's ``SceneObject``
        semantics, see docs/wire.md).

        Raises:
            ValueError: unknown target or unsupported operation.
        """
        if edit.op == "move" and edit.target in self._devices:
            d = self._devices[edit.target]
            if d.kind == "robot":
                p = self._pose[edit.target]
                if edit.position is not None:
                    p[:3] = edit.position
                if edit.orientation is not None:
                    p[3:] = edit.orientation
            else:
                old = self._fixed[edit.target]
                self._fixed[edit.target] = DevicePose(
                    edit.position if edit.position is not None else old.position,
                    edit.orientation if edit.orientation is not None else old.orientation)
        elif edit.op in ("move", "material"):
            objs = self.scene.sionna.objects
            if edit.target not in objs:
                raise ValueError(f"edit {edit.op}: unknown object {edit.target!r}")
            obj = objs[edit.target]
            if edit.op == "move":
                if edit.orientation is not None:
                    obj.orientation = sionna_orientation(edit.orientation)
                if edit.position is not None:
                    obj.position = [float(x) for x in edit.position]
            else:
                import sionna.rt as rt

                if not edit.material:
                    raise ValueError("edit material: no material given")
                obj.radio_material = rt.ITURadioMaterial(
                    f"live-{edit.material}-{edit.thickness}", edit.material,
                    thickness=float(edit.thickness or 0.1))
        else:
            raise ValueError(f"edit {edit.op!r} is not supported by LineTwin")
        self._edits.append(repr(edit))
        log.info("applied %s", edit)

    def command(self, cmd: Command) -> None:
        """``teleop`` (``robot``, ``linear`` m/s, ``angular`` rad/s); others are logged."""
        if cmd.op == "teleop":
            name = cmd.args.get("robot") or next(iter(self._pose), None)
            if name not in self._pose:
                raise ValueError(f"teleop: unknown robot {name!r}")
            self._v[name] = float(cmd.args.get("linear", self._v[name]))
            self._w[name] = float(cmd.args.get("angular", self._w[name]))
        else:
            raise ValueError(f"command {cmd.op!r} is not supported by LineTwin")
