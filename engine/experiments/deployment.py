"""The deployment loop of the paper's section IV-B, with a "real" room beside the twin.

Two worlds run side by side (``docs/casestudy.md`` defines every position):

* **reality**: a :class:`~isac_twin.twin.twin.Twin` of a *perturbed copy* of the room
  (objects shifted/rotated by a few cm, one material changed; or the
  unperturbed room) stands in for the physical lab. Its robot has the
  simulator's true pose (**truth**) and drifting wheel odometry
  (**odometry**, the paper's "ground truth"); its links are traced at the
  true pose and give the achievable rates and, in the realistic mode, the
  received pilots.
* **the twin**: the unperturbed room the fingerprint database was built
  from. The robot streams its odometry; the twin places its robot at
  ``T_cal(odometry)`` (**twin position**), where ``T_cal`` is the twin's
  imperfect mapping of the odometry start point (a few cm and a fraction of
  a degree, seeded): the paper's cause of the modelling error.

Each step, after the motion update (stage 5 of Algorithm 1, as a twin
estimator): the robot sends its estimate to the twin; the MDP is computed

* ``source="twin"`` (the paper's mode): by the twin's tracer at the twin
  position (a fingerprint generally not in the database), or
* ``source="real"``: from the real room's link at the true pose,

either straight from the tracer's delays (``mode="tracer"``) or estimated
from received pilots at ``snr_db`` (``mode="pilots"``); the robot localizes
with it (**estimate**). Open loop: the controller steers on odometry.
Closed loop: it steers on a complementary filter of the estimate and the
odometry increments (``fusion="blend"``: ``alpha`` weight of the estimate;
estimates farther than ``gate_m`` from the prediction are ignored as
outliers), or on an EKF over the odometry with the estimates as
Mahalanobis-gated fixes (``fusion="ekf"``, :mod:`isac_twin.localization.fusion`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..localization.baselines import METHODS, make_localizer
from ..localization.fingerprints import FingerprintDB, attach
from ..localization.fusion import PoseEKF
from ..localization.measurements import FeatureSpec, PilotSettings, observe_pilots, observe_tracer
from ..phy.network import NetworkPHY
from ..raytrace import device_poses
from ..robots import SensorOptions
from ..robots.control import controller_from_spec, path_from_spec
from ..scene.room import shell_objects
from ..scene.twin_scene import TwinScene, load_scene
from ..twin.twin import Twin
from ..utils.geometry import DevicePose, antenna_pose, planar_pose

log = logging.getLogger(__name__)

def perturb_scene(scene: TwinScene, *, seed: int = 0, shift_std: float = 0.03,
                  yaw_std_deg: float = 2.0, material: tuple[str, str] | None = None,
                  keep=None) -> dict:
    """Make ``scene`` a perturbed copy ("reality") of the twin's room, in place.

    Every object not in ``keep`` is shifted by ``N(0, shift_std)`` m in x and
    y and turned by ``N(0, yaw_std_deg)`` deg about z; one object's material
    is changed (``material = (object, ITU type)``; default: the first
    table-like wooden object becomes metal).

    Args:
        keep: names of the objects that stay put (default: the room's shell,
            :func:`isac_twin.scene.room.shell_objects`: walls, floor, ceiling, windows,
            from ``[room]`` tags or the geometry, whatever they are called).

    Returns:
        What was done: ``{"moved": {name: [dx, dy, dyaw_deg]}, "material": [name, old, new]}``.
    """
    keep = shell_objects(scene) if keep is None else frozenset(keep)
    rng = np.random.default_rng(seed)
    moved = {}
    for name in sorted(scene.objects):
        if name in keep:
            continue
        obj = scene.sionna.objects[name]
        pos = np.asarray(obj.position.numpy()).reshape(3)
        dx, dy = rng.normal(0.0, shift_std, 2)
        dyaw = rng.normal(0.0, math.radians(yaw_std_deg))
        scene.move_object(name, position=pos + [dx, dy, 0.0], orientation=[0.0, 0.0, dyaw])
        moved[name] = [float(dx), float(dy), float(math.degrees(dyaw))]
    if material is None:
        cands = [n for n in sorted(scene.objects) if n not in keep
                 and scene.objects[n].material == "wood"]
        cands = [n for n in cands if "table" in n.lower()] or cands
        material = (cands[0], "metal") if cands else None
    changed = None
    if material is not None:
        name, new = material
        old = scene.objects[name].material
        scene.set_material(name, new, 0.002 if new == "metal" else None)
        changed = [name, old, new]
    log.info("perturbed room: %d objects moved (shift std %.3f m, yaw std %.1f deg), "
             "material %s", len(moved), shift_std, yaw_std_deg, changed)
    return {"moved": moved, "material": changed}


@dataclass
class DeploymentSettings:
    """How the deployment loop runs.

    Attributes:
        source: ``"twin"`` (paper) or ``"real"``: where the MDP is computed.
        mode: ``"tracer"`` (delays from the tracer) or ``"pilots"``.
        snr_db: pilot SNR (mode ``"pilots"``), dB.
        perturb: the real room is a perturbed copy (else identical to the twin).
        closed_loop: steer on the estimate (filtered) instead of odometry.
        alpha: closed loop: weight of a new estimate in the navigation pose.
        gate_m: closed loop: an estimate farther than this from the predicted
            navigation pose is treated as an outlier and ignored, m.
        calib_std: ``(m, deg)`` std of the twin's initial-point mapping error.
        path: the path spec the robot follows (``[devices.path]`` form, any kind;
            default: the robot's own ``[devices.path]`` from twin.toml).
        robot: robot name (default: the first robot).
        method: localizer: ``"MCA"`` (the paper's), ``"MCA-angles"``,
            ``"LOS-fix"``, ``"PDP"`` or ``"kNN-CSI"``.
        fusion: closed loop: ``"blend"`` (odometry-predicted pose blended with
            gated estimates, weight ``alpha``) or ``"ekf"``
            (:class:`~isac_twin.localization.fusion.PoseEKF` over odometry with
            the estimates as gated fixes; the recorded estimate is then the
            fused antenna position).
        mca: :class:`~isac_twin.localization.baselines.MCA` keyword arguments.
        num_paths: measured MDP entries (J).
    """

    source: str = "twin"
    mode: str = "tracer"
    snr_db: float = 20.0
    perturb: bool = True
    closed_loop: bool = False
    alpha: float = 0.3
    gate_m: float = 0.5
    calib_std: tuple[float, float] = (0.02, 0.5)
    path: dict | None = None
    robot: str | None = None
    method: str = "MCA"
    mca: dict = field(default_factory=dict)
    num_paths: int = 9
    fusion: str = "blend"

    def __post_init__(self):
        if self.source not in ("twin", "real"):
            raise ValueError(f"source: expected 'twin' or 'real', got {self.source!r}")
        if self.mode not in ("tracer", "pilots"):
            raise ValueError(f"mode: expected 'tracer' or 'pilots', got {self.mode!r}")
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(map(repr, METHODS))}, "
                             f"got {self.method!r}")
        if self.fusion not in ("blend", "ekf"):
            raise ValueError(f"fusion: expected 'blend' or 'ekf', got {self.fusion!r}")
        if not 0 < self.alpha <= 1:
            raise ValueError(f"alpha: expected 0 < alpha <= 1, got {self.alpha}")


@dataclass
class StepRecord:
    """Positions (x, y of the robot antenna, m) and link figures of one step."""

    step: int
    time_s: float
    truth: np.ndarray
    odometry: np.ndarray
    twin: np.ndarray
    estimate: np.ndarray
    rates_bps: dict
    snr_db: dict


class Deployment:
    """Reality + twin + localizer, stepped together (see the module doc).

    Args:
        folder: the scene folder (twin.toml) of the twin's room.
        db: the fingerprint database built from the twin's room (checked).
        settings: :class:`DeploymentSettings`.
        seed: one seed (robot, sensors, perturbation, calibration, noise).
        dt: step, s.
        localizer: ``loc(obs) -> [3]`` (default MCA with ``settings.mca``).
        rate_every: compute the links' achievable rates (NetworkPHY, eqs. 1-4)
            every this many steps (NaN in between).
        extra_phy: ``{label: NetworkPHY}`` also evaluated on the same paths (e.g.
            another resource allocation); recorded as ``"AP1->robot1 (label)"``.
        real_scene: the real room as a loaded :class:`~isac_twin.scene.twin_scene.TwinScene` (e.g. a
            calibrated twin's deployment in the same reality as the original's);
            default a copy of ``folder``'s room, perturbed when ``settings.perturb``.
    """

    def __init__(self, folder, db: FingerprintDB, settings: DeploymentSettings | None = None,
                 *, seed: int = 0, dt: float = 0.25, localizer=None,
                 rate_every: int = 1, extra_phy: dict | None = None,
                 real_scene: TwinScene | None = None) -> None:
        self.settings = s = settings or DeploymentSettings()
        self.db = db
        self.twin = Twin(load_scene(folder), seed=seed, phy=False,
                         sensors=SensorOptions(lidar=False, imu=False))
        attach(self.twin, db)
        given = real_scene is not None
        real_scene = real_scene if given else load_scene(folder)
        self.perturbation = (perturb_scene(real_scene, seed=seed + 1)
                             if s.perturb and not given else None)
        # The PHY (rates) costs seconds per step for a 32 x 2 link: run it every
        # ``rate_every`` steps only, with the same NetworkPHY the twin would use.
        self.rate_every = max(1, int(rate_every))
        self.phy = NetworkPHY(real_scene.config)
        self.extra_phy = dict(extra_phy or {})
        self.reality = Twin(real_scene, seed=seed, dt=dt, phy=False,
                            sensors=SensorOptions(lidar=False, imu=False),
                            estimators=[self._estimate])
        cfg = self.twin.config
        robots = [d.name for d in cfg.devices if d.kind == "robot"]
        self.robot = s.robot or robots[0]
        self.dev = cfg.device(self.robot)
        self.spec = FeatureSpec.from_config(cfg)
        if localizer is None:
            localizer = make_localizer(s.method, db, self.spec, num_paths=s.num_paths,
                                       mca=s.mca)
        self.localizer = localizer
        self.pilots = PilotSettings(snr_db=s.snr_db, seed=seed)
        self.rng = np.random.default_rng([seed, 7])
        crng = np.random.default_rng([seed, 11])
        self.calib = (crng.normal(0, s.calib_std[0], 2),
                      math.radians(crng.normal(0, s.calib_std[1])))
        st = self.reality.agents[self.robot].state
        self.start = np.array([st.x, st.y, st.yaw])
        agent = self.reality.agents[self.robot]
        bounds = (real_scene.bounds_min[:2], real_scene.bounds_max[:2])
        if s.path is None and self.dev.path is None:
            raise ValueError(f"{cfg.path}: robot {self.robot!r} has no [devices.path]: give the "
                             "case study a path (circle, polyline, figure_eight or goal)")
        self.path_spec = dict(s.path if s.path is not None else self.dev.path)
        self.path = path_from_spec(self.path_spec, start=self.start[:2])
        self._ctl = controller_from_spec(self.path_spec, agent.spec, bounds=bounds)
        self.nav = self.start.copy()  # the pose the controller steers on [x, y, yaw]
        self.ekf = (PoseEKF(self.start, self.start,
                            antenna_offset=tuple(self.dev.antenna_offset[:2]))
                    if s.closed_loop and s.fusion == "ekf" else None)
        self._last_odom = self.start.copy()
        self.reality.set_controller(self.robot, self._control)
        # In the paper's mode the real room's links serve only the rates: trace
        # them on rate steps only (the twin's tracer does the MDP).
        if s.source != "real":
            self.reality.trace_schedule = lambda k: k % self.rate_every == 0
        self.records: list[StepRecord] = []
        self.rejected = 0  #: closed loop: estimates rejected by the gate

    # ------------------------------------------------------------ poses

    def twin_position(self, odom) -> np.ndarray:
        """``T_cal(odometry)``: where the twin puts the robot base, ``[x, y, yaw]``."""
        (dx, dy), dth = self.calib
        c, s = math.cos(dth), math.sin(dth)
        rel = np.asarray(odom[:2], float) - self.start[:2]
        xy = self.start[:2] + [c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]] + [dx, dy]
        return np.array([xy[0], xy[1], odom[2] + dth])

    def _antenna(self, pose_xyyaw) -> np.ndarray:
        return np.array(antenna_pose(planar_pose(*pose_xyyaw), self.dev.antenna_offset).position)

    def _control(self, state):
        st = state.copy()
        st.pose[0], st.pose[1], st.pose[5] = self.nav
        return self._ctl(st)

    # ------------------------------------------------------------ the estimator

    def _links_at(self, twin: Twin, antenna_xyz, yaw) -> list:
        poses = dict(device_poses(twin.config))
        poses[self.robot] = DevicePose(tuple(antenna_xyz), (0.0, 0.0, float(yaw)))
        links = twin.tracer(twin.scene, poses)
        return [links[(ap, self.robot)] for ap in self.db.ap_names]

    def observe(self, links: list):
        """Observation of ``links`` (per AP) in the configured mode."""
        if self.settings.mode == "tracer":
            return observe_tracer(links, self.spec, self.settings.num_paths)
        chans = [self.phy.channel(lp) for lp in links]
        need = METHODS.get(self.settings.method, ("mdp", "csi", "pdp", "dirs"))
        return observe_pilots(links, chans, self.spec, self.pilots, self.settings.num_paths,
                              rng=self.rng, features=need)

    def _estimate(self, reality: Twin, result) -> None:
        s = self.settings
        rs = result.robots[self.robot]
        odom = np.asarray(rs.odometry if rs.odometry is not None else
                          [rs.pose[0], rs.pose[1], rs.pose[5]], float)
        truth = np.array([rs.pose[0], rs.pose[1], rs.pose[5]])
        twin_pose = self.twin_position(odom)
        twin_ant = self._antenna(twin_pose)
        if s.source == "twin":
            links = self._links_at(self.twin, twin_ant, twin_pose[2])
        else:
            links = [result.links[(ap, self.robot)].paths for ap in self.db.ap_names]
        est = np.asarray(self.localizer(self.observe(links)), float)
        est[2] = twin_ant[2]
        rs.estimate = est
        # navigation pose for the next control
        d_odom = odom - self._last_odom
        self._last_odom = odom
        if self.ekf is not None:
            self.ekf.predict(odom)
            if not self.ekf.update(est[:2]):
                self.rejected += 1
            self.nav = self.ekf.pose
            est = np.array([*self.ekf.antenna_xy, est[2]])
            rs.estimate = est
        elif s.closed_loop:
            pred = self.nav + d_odom
            if np.linalg.norm(est[:2] - pred[:2]) <= s.gate_m:
                pred[:2] = (1 - s.alpha) * pred[:2] + s.alpha * est[:2]
            else:
                self.rejected += 1
            self.nav = np.array([pred[0], pred[1], odom[2]])
        else:
            self.nav = odom.copy()
        rates = {f"{lk.tx}->{lk.rx}": float("nan") for lk in self.twin.config.links}
        snrs = dict(rates)
        if result.step % self.rate_every == 0:
            sig = self.phy({lk: ls.paths for lk, ls in result.links.items()})
            for lk, ls in result.links.items():
                ls.rate_bps, ls.snr_db = sig[lk].rate_bps, sig[lk].snr_db
                rates[f"{lk[0]}->{lk[1]}"], snrs[f"{lk[0]}->{lk[1]}"] = ls.rate_bps, ls.snr_db
                # the rate a modem reaches ([link_adaptation] MCS table, EVM floor)
                ls.mcs_rate_bps, ls.mcs = sig[lk].mcs_rate_bps, sig[lk].mcs
                rates[f"{lk[0]}->{lk[1]} [MCS]"] = ls.mcs_rate_bps
            for label, phy in self.extra_phy.items():
                sig = phy({lk: ls.paths for lk, ls in result.links.items()})
                for lk in result.links:
                    rates[f"{lk[0]}->{lk[1]} ({label})"] = sig[lk].rate_bps
        self.records.append(StepRecord(
            step=result.step, time_s=result.time_s, truth=self._antenna(truth)[:2],
            odometry=self._antenna(odom)[:2], twin=twin_ant[:2], estimate=est[:2],
            rates_bps=rates, snr_db=snrs))

    # ------------------------------------------------------------ running

    def run(self, steps: int, on_step=None) -> list[StepRecord]:
        """Run ``steps`` steps of the reality twin (the estimator runs inside)."""
        for res in self.reality.run(steps):
            if on_step is not None:
                on_step(res, self.records[-1])
        return self.records

    def lap_steps(self) -> int:
        """Steps for about one lap of the path (a closed path; to the end of an open
        one, with its final slow-down) at the robot's cruise speed."""
        extra = 2 if self.path.closed else 2 + int(math.ceil(2.0 / self.reality.dt))
        return int(math.ceil(self.path.length / (0.95 * self._ctl.speed)
                             / self.reality.dt)) + extra


def errors(records: list[StepRecord]) -> dict[str, np.ndarray]:
    """Per-step errors, m: ``positioning`` (estimate vs odometry, the paper's),
    ``modelling`` (twin vs odometry, the paper's), ``estimate_vs_truth``,
    ``odometry_vs_truth``, ``twin_vs_truth``."""
    g = {k: np.array([getattr(r, k) for r in records]) for k in
         ("truth", "odometry", "twin", "estimate")}
    d = lambda a, b: np.linalg.norm(g[a] - g[b], axis=1)  # noqa: E731
    return {"positioning": d("estimate", "odometry"), "modelling": d("twin", "odometry"),
            "estimate_vs_truth": d("estimate", "truth"),
            "odometry_vs_truth": d("odometry", "truth"),
            "twin_vs_truth": d("twin", "truth")}


def summarize(err: np.ndarray) -> dict:
    """RMSE, median, P90, max of ``err`` (m)."""
    err = np.asarray(err, float)
    if err.size == 0:
        return {"rmse": float("nan"), "median": float("nan"), "p90": float("nan"),
                "max": float("nan")}
    return {"rmse": float(np.sqrt(np.mean(err ** 2))), "median": float(np.median(err)),
            "p90": float(np.percentile(err, 90)), "max": float(np.max(err))}
