"""The twin's own localizer: a stage-5 estimator that fills ``robots[r].estimate``.

:class:`TwinLocalizer` is what ``[localization]`` in ``twin.toml`` gives any
:class:`~isac_twin.twin.twin.Twin` (``Twin`` appends it to its ``estimators`` hook;
see ``docs/config.md``). Every step with traced links, for every robot:

1. the observation of its links from every database AP: ``mode="pilots"``
   received pilots at ``snr_db`` on the step's eq.-4 channel
   (:func:`~isac_twin.localization.measurements.observe_pilots`, only the
   features the method needs), or ``mode="tracer"`` the traced paths;
2. the fix of the configured localizer (``method``) over the fingerprint
   database of the twin's room (:func:`cached_database`, built once);
3. ``fusion="ekf"``: a :class:`~isac_twin.localization.fusion.PoseEKF` per robot,
   predicted with the robot's odometry and updated with the gated fix;
   ``"none"``: the fix itself.

``result.robots[r].estimate`` is ``[x, y, z]`` of the robot's antenna (m);
it is also published on the twin's bus as ``/<robot>/fingerprint``
(``isac_twin_msgs/Fingerprint``: estimate, ``source`` = the method, the
measured MDP of the first AP), so ``record`` and ``record --connect`` store
it with every other topic. Steps without links (a trace schedule) only
predict. A reset of the twin (step index back to 0) restarts the filters.
"""

from __future__ import annotations

import numpy as np

from ..bus.msgs import Header
from ..bus.twin_msgs import Fingerprint
from ..phy.network import NetworkPHY
from ..utils.geometry import antenna_pose, planar_pose
from .baselines import METHODS, make_localizer
from .fingerprints import FingerprintDB, attach, cached_database
from .fusion import PoseEKF
from .measurements import FeatureSpec, PilotSettings, observe_pilots, observe_tracer

__all__ = ["TwinLocalizer"]


class TwinLocalizer:
    """Stage-5 estimator ``loc(twin, result)`` (see the module doc).

    Args:
        config: the twin's :class:`~isac_twin.scene.config.TwinConfig`.
        settings: its :class:`~isac_twin.scene.config.LocalizationConfig`.
        db: the fingerprint database of the twin's room.
        seed: pilot-noise seed.
    """

    def __init__(self, config, settings, db: FingerprintDB, *, seed: int = 0) -> None:
        if settings.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, "
                             f"got {settings.method!r}")
        self.settings = settings
        self.db = db
        self.spec = FeatureSpec.from_config(config)
        self.localizer = make_localizer(settings.method, db, self.spec)
        self.features = METHODS[settings.method]
        self.pilots = PilotSettings(snr_db=settings.snr_db, seed=seed)
        self.phy = NetworkPHY(config) if settings.mode == "pilots" else None
        self.robots = {d.name: d for d in config.devices if d.kind == "robot"}
        self.seed = int(seed)
        self.rng = np.random.default_rng([self.seed, 13])
        self.filters: dict[str, PoseEKF] = {}
        self._last_step = -1
        self._bus = self._node = None

    @classmethod
    def for_twin(cls, twin) -> TwinLocalizer:
        """The localizer ``twin.config.localization`` asks for; the database is
        loaded from (or built into) ``cache_dir`` and registered with the twin,
        so an edit of the room lists it in ``twin.stale_databases()``."""
        s = twin.config.localization
        if s is None:
            raise ValueError(f"{twin.config.path}: no [localization] table")
        cache = twin.config.folder / s.cache_dir
        db = cached_database(twin.scene, spacing=s.spacing_m, cache_dir=cache)
        attach(twin, db)
        loc = cls(twin.config, s, db, seed=twin.seed)
        loc._publisher(twin)  # topics advertised now: recorders see the first step
        return loc

    def _publisher(self, twin):
        """The localizer's node on the twin's bus (a reset replaces the bus)."""
        if twin.bus is not self._bus:
            self._bus = twin.bus
            self._node = twin.bus.node("localizer")
            for name in self.robots:
                self._node.advertise(f"/{name}/fingerprint", Fingerprint)
        return self._node

    def _fix(self, twin, result, robot: str):
        links = []
        for ap in self.db.ap_names:
            ls = result.links.get((ap, robot))
            if ls is None:
                return None, None
            links.append(ls.paths)
        if self.settings.mode == "tracer":
            obs = observe_tracer(links, self.spec)
        else:
            chans = [self.phy.channel(lp) for lp in links]
            obs = observe_pilots(links, chans, self.spec, self.pilots, rng=self.rng,
                                 features=self.features)
        return np.asarray(self.localizer(obs), float), obs

    def __call__(self, twin, result) -> None:
        if result.step <= self._last_step:  # the twin was reset
            self.filters.clear()
            self.rng = np.random.default_rng([self.seed, 13])
        self._last_step = result.step
        for name, dev in self.robots.items():
            rs = result.robots.get(name)
            if rs is None:
                continue
            odom = (np.asarray(rs.odometry, float) if rs.odometry is not None
                    else np.array([rs.pose[0], rs.pose[1], rs.pose[5]], float))
            height = antenna_pose(planar_pose(*odom), dev.antenna_offset).position[2]
            fix, obs = self._fix(twin, result, name) if result.links else (None, None)
            if self.settings.fusion == "none":
                if fix is not None:
                    rs.estimate = np.array([fix[0], fix[1], height])
                    self._publish(twin, result, name, rs.estimate, obs)
                continue
            ekf = self.filters.get(name)
            if ekf is None:
                ekf = self.filters[name] = PoseEKF(
                    odom, odom, antenna_offset=tuple(dev.antenna_offset[:2]),
                    fix_std_m=self.settings.fix_std_m, initial_std=(0.5, 0.2))
            else:
                ekf.predict(odom)
            if fix is not None:
                ekf.update(fix[:2])
            xy = ekf.antenna_xy
            rs.estimate = np.array([xy[0], xy[1], height])
            self._publish(twin, result, name, rs.estimate, obs)

    def _publish(self, twin, result, robot: str, estimate, obs) -> None:
        mdp = np.zeros(0)
        if obs is not None:  # the first AP's measured lengths (MDP, else the joint estimate)
            mdp = obs.lengths[0][np.isfinite(obs.lengths[0])]
            if mdp.size == 0 and obs.paths and obs.paths[0] is not None:
                mdp = np.asarray(obs.paths[0].distances_m, float)
        self._publisher(twin).publish(f"/{robot}/fingerprint", Fingerprint(
            header=Header(stamp=result.time_s, frame_id="map"), robot=robot,
            source=f"{self.settings.method}/{self.settings.mode}", mdp=mdp,
            estimate=np.asarray(estimate, float), confidence=1.0))
