"""``RadarEstimator``: ISAC sensing as a twin estimator (stage 5 of Algorithm 1).

Each step, for every sensing link: robots (and tagged objects) are posed as
sensing targets, echo + clutter paths are traced
(:class:`~isac_twin.sensing.tracer.SensingTracer`), the eq.-4 channel is
synthesised, the sensing REs are received with noise (``y = H x + z``),
divided by the known symbols, background-subtracted and processed by
:class:`~isac_twin.sensing.radar.OFDMRadar`; detections are geolocated
(range ellipse x azimuth) and fed to one multi-target
:class:`~isac_twin.sensing.tracker.KalmanTracker`. Detections and confirmed
tracks are published on ``/sensing/detections``
(:class:`~isac_twin.bus.sensing_msgs.Detections`) and stored on the step result as
``result.sensing`` (a :class:`SensingStep`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..bus.sensing_msgs import DETECTIONS_TOPIC, Detections, advertise
from ..errors import SensingError
from ..phy.ofdm import ResourceGrid
from ..utils.geometry import DevicePose, sionna_orientation
from ..utils.threads import one_blas_thread
from .clutter import BackgroundSubtractor
from .geometry import locate
from .link import SensingLinkSpec, SensingReceiver, echo_channel
from .radar import OFDMRadar
from .tracer import BURGER_SIZE, SensingTracer, TargetSpec
from .tracker import KalmanTracker, Track

log = logging.getLogger(__name__)

__all__ = ["RadarEstimator", "SensingStep", "SensingJob", "grid_from_config"]


def grid_from_config(config) -> ResourceGrid:
    """The step's :class:`ResourceGrid` from ``config.ofdm``."""
    o = config.ofdm
    return ResourceGrid(o.num_subcarriers, o.subcarrier_spacing_hz, o.num_symbols,
                        o.cyclic_prefix_samples)


@dataclass
class SensingStep:
    """What the radar estimator produced in one step.

    Attributes:
        detections: link name -> list of :class:`Detection` (with positions).
        maps: link name -> :class:`RangeDopplerMap` (only if ``keep_maps``).
        tracks: confirmed tracks after this step.
        truth: target name -> ``[3]`` centre (m) used for the echo.
        step, time_s: the twin step that was sensed and its time (s); a frame
            computed off the stepping thread is delivered on a later step
            (:class:`~isac_twin.sensing.worker.SensingWorker`).
    """

    detections: dict = field(default_factory=dict)
    maps: dict = field(default_factory=dict)
    tracks: list = field(default_factory=list)
    truth: dict = field(default_factory=dict)
    step: int | None = None
    time_s: float | None = None


@dataclass
class SensingJob:
    """What one radar frame needs from the twin, taken on the stepping thread
    (:meth:`RadarEstimator.prepare`), so :meth:`RadarEstimator.compute` needs
    nothing else.

    Attributes:
        step, time_s: the sensed step and its time (s).
        dt: time since the previous frame (s), for the tracker.
        links: the due :class:`SensingLinkSpec`.
        poses: device name -> :class:`DevicePose` at the sensed step.
        truth: target name -> ``[3]`` centre (m).
        grid: the OFDM grid.
        contains: ``contains(point, tol=) -> bool``, inside the room.
        targets: the robot targets (:class:`TargetSpec`) posed in the scene for
            this frame.
    """

    step: int
    time_s: float
    dt: float
    links: list
    poses: dict
    truth: dict
    grid: ResourceGrid
    contains: object
    targets: list = field(default_factory=list)


class RadarEstimator:
    """Twin estimator ``est(twin, result)`` running ISAC radar every step.

    Args:
        links: sensing links (:class:`SensingLinkSpec`); default: parsed from
            the twin config's ``[[sensing]]`` tables.
        robot_targets: make every robot a target.
        object_targets: scene object names tagged as (static) targets.
        sigma: radar cross-section of each target [m^2].
        target_size: robot cuboid (length, width, height) [m].
        background: ``"ema"``, ``"reference"`` (clutter-only channel of the
            empty room, noise-free) or ``"none"``.
        beta: EMA weight of the background estimate.
        tracer_kw: keyword args of :class:`SensingTracer`.
        radar_kw: keyword args of :class:`OFDMRadar`.
        tracker: a :class:`KalmanTracker` (default one is built).
        seed: seed of symbols and noise.
        keep_maps: keep range-Doppler maps in ``result.sensing``.
        publish: publish :class:`Detections` on ``topic``.
    """

    def __init__(self, links: list[SensingLinkSpec] | None = None, *,
                 robot_targets: bool = True, object_targets: tuple = (),
                 sigma: float = 0.5, target_size=BURGER_SIZE, background: str = "ema",
                 beta: float = 0.1, tracer_kw: dict | None = None,
                 radar_kw: dict | None = None, tracker: KalmanTracker | None = None,
                 seed: int = 0, keep_maps: bool = False, publish: bool = True,
                 topic: str = DETECTIONS_TOPIC) -> None:
        self.links = None if links is None else list(links)
        self.robot_targets = bool(robot_targets)
        self.object_targets = tuple(object_targets)
        self.sigma = float(sigma)
        self.target_size = tuple(float(v) for v in target_size)
        self.background = background
        self.beta = beta
        self.tracer_kw = dict(tracer_kw or {})
        self.radar_kw = dict(radar_kw or {})
        self.tracker = tracker or KalmanTracker()
        self.seed = int(seed)
        self.keep_maps = bool(keep_maps)
        self.publish = bool(publish)
        self.topic = topic
        self.tracer: SensingTracer | None = None
        self._scene = None
        self._state: dict = {}
        self._clutter_h: dict = {}
        self._node = None
        self._bus = None
        self._last_t: float | None = None
        self.history: list[SensingStep] = []
        self._calls = 0

    def attach(self, bus) -> None:
        """Advertise the detections topic on ``bus`` now (so the registry and
        recorders list it before the first detection)."""
        if self.publish and self._bus is not bus:
            self._bus = bus
            self._node = advertise(bus, self.topic)

    # ------------------------------------------------------------------ setup

    def setup(self, scene) -> None:
        """Trace on ``scene`` (a :class:`~isac_twin.scene.twin_scene.TwinScene`; its config
        names the devices and the grid): a new tracer, receivers and
        background per link (called by the first :meth:`prepare` with the
        twin's scene, and by the radar's process with its replica)."""
        if self.links is None:
            from .config import parse_sensing

            self.links = parse_sensing(scene.config)
        if not self.links:
            raise SensingError("RadarEstimator: no sensing links (pass links= or add "
                               "[[sensing]] tables to twin.toml)")
        names = {d.name for d in scene.config.devices}
        for s in self.links:
            for n in (s.tx, s.rx):
                if n not in names:
                    raise SensingError(f"sensing link {s.name!r}: unknown device {n!r}")
        self._scene = scene
        self.tracer = SensingTracer(scene, **self.tracer_kw)
        grid = grid_from_config(scene.config)
        for i, s in enumerate(self.links):
            rx = SensingReceiver(s, grid, seed=self.seed + 7919 * i)
            self._state[s.name] = {
                "spec": s, "rx": rx, "radar": None, "orientation": None,
                "bg": BackgroundSubtractor(self.background, self.beta, s.name)}
        for name in self.object_targets:
            if name not in scene.objects:
                raise SensingError(f"RadarEstimator: object_targets: no object {name!r} "
                                   f"in the scene")
            o = scene.objects[name]
            lo, hi = np.asarray(o.bounds_min), np.asarray(o.bounds_max)
            self.tracer.set_target(TargetSpec(name=name, size=tuple(hi - lo),
                                              sigma=self.sigma, position=(lo + hi) / 2))

    def _radar(self, st, pose: DevicePose) -> OFDMRadar:
        spec: SensingLinkSpec = st["spec"]
        ori = sionna_orientation(pose.orientation)
        if st["radar"] is None or st["orientation"] != ori:
            kw = dict(self.radar_kw)
            kw.setdefault("range_method", spec.range_method)
            st["radar"] = OFDMRadar(st["rx"].resource_set,
                                    self._scene.config.scene.frequency_hz,
                                    rx_array=spec.rx_array, rx_orientation=ori,
                                    estimate_angles=spec.estimate_angles, **kw)
            st["orientation"] = ori
        return st["radar"]

    def update_targets(self, twin, result) -> list[TargetSpec]:
        """Pose every robot target from the step's truth; returns their specs."""
        specs = []
        if not self.robot_targets:
            return specs
        h = self.target_size[2]
        for name, rs in result.robots.items():
            x, y, z, _, _, yaw = (float(v) for v in rs.pose[:6])
            v = float(rs.velocity[0])
            specs.append(TargetSpec(
                name=name, size=self.target_size, sigma=self.sigma,
                position=np.array([x, y, z + h / 2]), yaw=yaw,
                velocity=np.array([v * np.cos(yaw), v * np.sin(yaw), 0.0])))
        self.pose_targets(specs)
        return specs

    def pose_targets(self, specs) -> None:
        """Put the targets ``specs`` (:class:`TargetSpec`) into this radar's scene
        (the radar's process poses its replica's from a job's ``targets``)."""
        for spec in specs:
            self.tracer.set_target(spec)

    # ------------------------------------------------------------------ step

    def __call__(self, twin, result) -> SensingStep | None:
        """Sense on the links due this call (``SensingLinkSpec.every``); sets and
        returns ``result.sensing`` (None when no link is due). The synchronous
        path: :meth:`prepare`, :meth:`compute` and :meth:`deliver` in a row."""
        job = self.prepare(twin, result)
        if job is None:
            result.sensing = None
            return None
        out = self.compute(job)
        self.deliver(twin, out)
        result.sensing = out
        return out

    def frame_due(self) -> bool:
        """A link is due on the next call (``SensingLinkSpec.every``); False before
        the first call sets the links up."""
        return bool(self.links) and any(self._calls % max(int(s.every), 1) == 0
                                        for s in self.links)

    def prepare(self, twin, result) -> SensingJob | None:
        """The part of a frame that reads or changes the twin (on the stepping
        thread): the links due this call, the robot targets posed in the Sionna
        scene from the step's truth, a snapshot of the device poses. None when no
        link is due (the call still counts for ``every``)."""
        if self.tracer is None or self._scene is not twin.scene:
            self.setup(twin.scene)
        call, self._calls = self._calls, self._calls + 1
        due = [s for s in self.links if call % max(int(s.every), 1) == 0]
        if not due:
            return None
        targets = self.update_targets(twin, result)
        dt = twin.dt if self._last_t is None else max(result.time_s - self._last_t, 1e-9)
        self._last_t = result.time_s
        return SensingJob(step=result.step, time_s=result.time_s, dt=dt, links=due,
                          poses=twin.device_poses(),
                          truth={t.name: t.position for t in targets},
                          grid=grid_from_config(twin.config), contains=twin.scene.contains,
                          targets=targets)

    def compute(self, job: SensingJob) -> SensingStep:
        """Trace, receive, process and track one frame (any thread; it touches
        neither the twin nor its bus, only this estimator's own state: tracer,
        noise streams, background, tracker, in frame order)."""
        one_blas_thread()  # as the twin's steps: the same bits on any thread
        poses, grid = job.poses, job.grid
        traced = self.tracer(poses, [(s.tx, s.rx) for s in job.links])
        out = SensingStep(truth=job.truth, step=job.step, time_s=job.time_s)
        measurements = []
        for s in job.links:
            st = self._state[s.name]
            ep = traced[(s.tx, s.rx)]
            key = id(ep.clutter)
            hc = self._clutter_h.get(s.name)
            if hc is None or hc[0] != key:
                hc = (key, echo_channel(ep.clutter, grid, s.rx_array))
                self._clutter_h[s.name] = hc
                bg = st["bg"]
                if bg.mode == "reference":
                    rs = st["rx"].resource_set
                    bg.set_reference(hc[1][np.ix_(rs.symbol_indices, rs.subcarrier_indices)])
            h = echo_channel(ep.echo, grid, s.rx_array) + hc[1]
            radar = self._radar(st, poses[s.rx])
            y = st["rx"].receive(h)
            h_hat = radar.channel_estimate(y, st["rx"].symbols)
            dets, rd = radar.process(st["bg"](h_hat))
            for d in dets:
                d.position = locate(d.path_length_m, d.azimuth_rad, d.zenith_rad,
                                    poses[s.tx].position, poses[s.rx].position,
                                    s.target_height_m)
                if d.position is not None and job.contains(d.position, tol=0.3):
                    measurements.append(d.position[:2])
                elif d.position is not None:
                    d.position = None
            out.detections[s.name] = dets
            if self.keep_maps:
                out.maps[s.name] = rd
        out.tracks = [_copy_track(t)
                      for t in self.tracker.update(np.array(measurements), job.dt)]
        return out

    def deliver(self, twin, out: SensingStep) -> None:
        """Keep a computed frame in :attr:`history` and publish it on the twin's
        bus, stamped with the time it sensed (``out.time_s``), on the stepping thread."""
        self.history.append(out)
        if self.publish:
            self._publish(twin, out.time_s, out)

    def _publish(self, twin, stamp: float, out: SensingStep) -> None:
        self.attach(twin.bus)
        dets = [d for ds in out.detections.values() for d in ds]
        msg = Detections(link="*" if len(out.detections) != 1 else next(iter(out.detections)))
        msg.header.stamp = float(stamp)
        msg.path_length = np.array([d.path_length_m for d in dets])
        msg.range_rate = np.array([d.range_rate_mps for d in dets])
        msg.azimuth = np.array([d.azimuth_rad for d in dets])
        msg.zenith = np.array([d.zenith_rad for d in dets])
        msg.snr_db = np.array([d.snr_db for d in dets])
        msg.position = np.array([d.position if d.position is not None else np.full(3, np.nan)
                                 for d in dets]).reshape(-1, 3)
        msg.track_id = np.array([t.id for t in out.tracks], dtype=np.int64)
        msg.track_position = np.array([t.position for t in out.tracks]).reshape(-1, 2)
        msg.track_velocity = np.array([t.velocity for t in out.tracks]).reshape(-1, 2)
        self._node.publish(self.topic, msg)


def _copy_track(t: Track) -> Track:
    return Track(id=t.id, x=t.x.copy(), P=t.P.copy(), hits=t.hits, misses=t.misses,
                 age=t.age, confirmed=t.confirmed)
