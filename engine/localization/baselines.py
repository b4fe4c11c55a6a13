"""Localizers over a :class:`~isac_twin.localization.fingerprints.FingerprintDB`.

Every localizer is a callable ``loc(obs: Observation) -> [3]`` position (m)
with a ``name``:

* :class:`MCA`: multipath component analysis on the MDP (the paper's method;
  :class:`~isac_twin.localization.mca.MCALocalizer` underneath).
* :class:`MCAAngles`: MCA whose matching distance adds the departure
  direction at multi-antenna APs (joint delay-direction estimation); single
  antennas fall back to length.
* :class:`LosFix`: geometric fix from a multi-antenna AP's line-of-sight
  path (range + azimuth), no database look-up.
* :class:`KnnCsi`: weighted kNN on CSI amplitude: ``|H|^2`` in dB averaged
  over the robot's antennas, at a decimated set of subcarriers and every AP
  antenna; the database CSI is synthesized from the database paths with
  :mod:`isac_twin.phy` (robot array at yaw 0; the receive-antenna average
  makes the feature nearly independent of the robot's heading).
* :class:`PdpMatch`: weighted kNN on the power-delay profile in dB (what the
  band resolves: paths convolved with the Dirichlet kernel of N subcarriers).

kNN distances are Euclidean per AP divided by the AP's feature size, summed
over APs (so a 32-antenna AP does not drown a single-antenna one); the
estimate is the ``1/d``-weighted mean of the ``k`` nearest points.
"""

from __future__ import annotations

import logging

import numpy as np

from ..phy.arrays import r_hat
from ..phy.directions import DelayDirectionProfile
from .fingerprints import FingerprintDB
from .mca import MCALocalizer
from .measurements import FeatureSpec, Observation, csi_from_paths, front_directions, pdp_from_paths
from .measurements import db as to_db

log = logging.getLogger(__name__)


class MCA:
    """MCA on the ``num_paths`` strongest database paths per AP.

    Args:
        db: the database.
        eps: matching radius, m.
        k: k-best weighted refinement.
        num_paths: strongest database paths per point and AP used as the fingerprint.
        num_measured: strongest measured paths used (default ``num_paths``).
        cluster_m: if > 0, the database fingerprint is band-limited like an
            estimated MDP: of the ``max_paths`` stored paths, those closer than
            ``cluster_m`` in length are merged (power-weighted mean length,
            summed power) and the ``num_paths`` strongest clusters kept. Use it
            for MDPs estimated from pilots (an 80 MHz band resolves clusters,
            not the tracer's individual paths).
    """

    name = "MCA"

    def __init__(self, db: FingerprintDB, *, eps: float = 0.5, k: int = 4, num_paths: int = 9,
                 num_measured: int | None = None, cluster_m: float = 0.0) -> None:
        free = db.free_indices
        self.db = db
        self.free = free
        self.num_paths = int(num_paths)
        self.num_measured = int(num_measured or num_paths)
        lengths = db.lengths[free]
        if cluster_m > 0:
            lengths = cluster_lengths(lengths, db.power[free], cluster_m, self.num_paths)
        self.loc = MCALocalizer(db.points[free], lengths[:, :, :self.num_paths], eps=eps, k=k)

    def __call__(self, obs: Observation) -> np.ndarray:
        return self.loc(obs.lengths[:, :self.num_measured]).position


class MCAAngles(MCA):
    """MCA whose matching distance combines path length and departure direction.

    The database fingerprint of every AP with more than one antenna is its
    ``num_paths`` strongest traced paths with their departure directions
    ``r_hat(theta_t, phi_t)`` folded into the array's front half-space
    (:func:`~isac_twin.localization.measurements.front_directions`: the array
    cannot tell a path leaving backwards from its mirror image); a measured
    path with a direction (from :attr:`Observation.paths`, i.e. joint
    delay-direction estimation at that AP) is matched by ``sqrt(dd^2 + (angle_weight_m |k - k_db|)^2)``
    (:class:`~isac_twin.localization.mca.MCALocalizer`). Single-antenna APs, and
    observations without directions, fall back to the delay-only MDP.

    Each measured path's score is weighted by its power relative to the
    strongest path of its AP (estimated clusters that match no single traced
    path are weak; the line of sight, strong and exact, dominates), and by
    ``length_only_weight`` at APs without directions (a length is one
    constraint, a length with a direction three; a delay-only MDP also holds
    the spurious cluster components the directions would have separated).

    Args:
        db: the database.
        spec: the :class:`FeatureSpec` (which APs have arrays, their orientations).
        angle_weight_m: metres per unit of direction chord.
        length_only_weight: score weight of APs matched by length only, in [0, 1].
        power_weighted: weight scores by relative path power (``False``: all 1).
        eps, k, num_paths, num_measured: as :class:`MCA` (no clustering: the
            directions separate what the band merges in length).
    """

    name = "MCA-angles"

    def __init__(self, db: FingerprintDB, spec: FeatureSpec, *, eps: float = 0.5, k: int = 4,
                 num_paths: int = 9, num_measured: int | None = None,
                 angle_weight_m: float = 3.0, length_only_weight: float = 0.3,
                 power_weighted: bool = True) -> None:
        if not 0 <= length_only_weight <= 1:
            raise ValueError(f"length_only_weight: expected a value in [0, 1], "
                             f"got {length_only_weight}")
        self.length_only_weight = float(length_only_weight)
        self.power_weighted = bool(power_weighted)
        free = db.free_indices
        self.db, self.free, self.spec = db, free, spec
        self.num_paths = int(num_paths)
        self.num_measured = int(num_measured or num_paths)
        self.multi = np.array([spec.arrays[ap].num_ant > 1 for ap in db.ap_names])
        lengths = db.lengths[free][:, :, :self.num_paths]
        dirs = r_hat(db.theta_t[free][:, :, :self.num_paths],
                     db.phi_t[free][:, :, :self.num_paths])  # [P, A, L, 3]
        for a, ap in enumerate(db.ap_names):
            dirs[:, a] = front_directions(dirs[:, a], self._orientation(ap))
        dirs[:, ~self.multi] = np.nan
        dirs[~np.isfinite(lengths)] = np.nan
        self.loc = MCALocalizer(db.points[free], lengths, eps=eps, k=k, directions=dirs,
                                angle_weight_m=angle_weight_m)

    def _orientation(self, ap: str):
        return self.spec.orientations.get(ap, (0.0, 0.0, 0.0))

    def measured(self, obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``[A, J]`` lengths (m), ``[A, J, 3]`` directions (NaN: none) and
        ``[A, J]`` score weights of ``obs``."""
        J = self.num_measured
        A = len(self.db.ap_names)
        lengths = np.full((A, J), np.nan)
        dirs = np.full((A, J, 3), np.nan)
        wts = np.zeros((A, J))
        for a, ap in enumerate(self.db.ap_names):
            prof = obs.paths[a] if a < len(obs.paths) else None
            if self.multi[a] and prof is not None:
                j = min(len(prof), J)
                lengths[a, :j] = prof.distances_m[:j]
                dirs[a, :j] = front_directions(prof.directions[:j], self._orientation(ap))
                power, scale = np.asarray(prof.powers[:j], float), 1.0
            else:
                j = min(obs.lengths.shape[1], J)
                lengths[a, :j] = obs.lengths[a, :j]
                power, scale = np.asarray(obs.powers[a, :j], float), self.length_only_weight
            ok = np.isfinite(lengths[a, :j])
            if self.power_weighted and ok.any() and power[ok].max() > 0:
                wts[a, :j] = np.where(ok, np.clip(power / power[ok].max(), 0.0, 1.0), 0.0)
            else:
                wts[a, :j] = ok
            wts[a] *= scale
        return lengths, dirs, wts

    def __call__(self, obs: Observation) -> np.ndarray:
        lengths, dirs, wts = self.measured(obs)
        return self.loc(lengths, dirs, wts).position


class LosFix:
    """Geometric fix from one multi-antenna AP's line-of-sight path: range + azimuth.

    The line-of-sight component is the shortest estimated path within
    ``los_window_db`` of the strongest (:attr:`Observation.paths` of the AP);
    with the AP position ``a`` and the robot antenna height ``h`` (the
    database's), the horizontal range is ``r = sqrt(d^2 - (a_z - h)^2)`` and the
    fix ``a_xy + r k_xy / |k_xy|`` (``k`` the departure direction): range and
    azimuth only, the elevation of a few-row array being the weakest of the
    three measurements. No database look-up; the fix is off the floor grid.

    Args:
        db: the database (AP positions and names, antenna height).
        spec: the :class:`FeatureSpec` (which APs have arrays).
        ap: the AP used (default: the first with more than one antenna).
        los_window_db: power window for the line-of-sight choice, dB.

    Raises:
        ValueError: no multi-antenna AP.
    """

    name = "LOS-fix"

    def __init__(self, db: FingerprintDB, spec: FeatureSpec, *, ap: str | None = None,
                 los_window_db: float = 10.0) -> None:
        multi = [n for n in db.ap_names if spec.arrays[n].num_ant > 1]
        if ap is None and not multi:
            raise ValueError("LOS-fix needs an access point with more than one antenna; "
                             f"{db.ap_names} are all single antennas")
        self.ap = ap or multi[0]
        if self.ap not in multi:
            raise ValueError(f"ap: {self.ap!r} is not a multi-antenna AP of the database "
                             f"({multi})")
        self.index = db.ap_names.index(self.ap)
        self.position = np.asarray(db.meta["ap_positions"][self.index], float)
        self.height = db.height
        self.window = 10 ** (-abs(los_window_db) / 10)
        self.fallback = db.points[db.free_indices].mean(axis=0)

    def __call__(self, obs: Observation) -> np.ndarray:
        prof = obs.paths[self.index] if self.index < len(obs.paths) else None
        if prof is None or len(prof) == 0:
            return self.fallback.copy()  # nothing measured: the database's centre
        strong = prof.powers >= prof.powers.max() * self.window
        j = np.flatnonzero(strong)[np.argmin(prof.distances_m[strong])]
        d, k = float(prof.distances_m[j]), prof.directions[j]
        dz = self.position[2] - self.height
        r = np.sqrt(max(d * d - dz * dz, 0.0))
        kh = np.hypot(k[0], k[1])
        u = k[:2] / kh if kh > 0 else np.zeros(2)
        return np.array([self.position[0] + r * u[0], self.position[1] + r * u[1], self.height])


def cluster_lengths(lengths, power, cluster_m: float, keep: int) -> np.ndarray:
    """Merge paths closer than ``cluster_m`` (m) in length, per point and AP.

    Args:
        lengths, power: ``[P, A, L]`` (NaN / 0 pads).
        keep: clusters kept per point and AP (strongest first).

    Returns:
        ``[P, A, keep]`` cluster lengths (power-weighted means), NaN pads.
    """
    P, A, L = lengths.shape
    order = np.argsort(np.where(np.isfinite(lengths), lengths, np.inf), axis=2)
    d = np.take_along_axis(lengths, order, axis=2)
    p = np.take_along_axis(np.where(np.isfinite(lengths), power, 0.0), order, axis=2)
    gap = np.diff(d, axis=2)
    new = np.concatenate([np.ones((P, A, 1), bool), ~(gap < cluster_m)], axis=2)
    cid = np.cumsum(new, axis=2) - 1  # [P, A, L] cluster index per path
    ok = np.isfinite(d)
    flat = (np.arange(P * A)[:, None] * L + cid.reshape(P * A, L))[ok.reshape(P * A, L)]
    w = p[ok]
    psum = np.bincount(flat, weights=w, minlength=P * A * L).reshape(P, A, L)
    dsum = np.bincount(flat, weights=w * d[ok], minlength=P * A * L).reshape(P, A, L)
    cnt = np.bincount(flat, minlength=P * A * L).reshape(P, A, L)
    with np.errstate(invalid="ignore", divide="ignore"):
        cl = np.where(cnt > 0, dsum / np.where(psum > 0, psum, 1.0), np.nan)
    cl = np.where((cnt > 0) & (psum <= 0), np.nan, cl)
    strongest = np.argsort(-np.where(np.isfinite(cl), psum, -1.0), axis=2)[:, :, :keep]
    return np.take_along_axis(cl, strongest, axis=2)


def _weighted_knn(dist: np.ndarray, pos: np.ndarray, k: int) -> np.ndarray:
    k = min(k, len(dist))
    idx = np.argpartition(dist, k - 1)[:k]
    w = 1.0 / np.maximum(np.sqrt(dist[idx]), 1e-9)
    return (w[:, None] * pos[idx]).sum(0) / w.sum()


class KnnCsi:
    """Weighted kNN on CSI amplitude (see the module doc).

    Args:
        db: the database (must keep the path angles and coefficients).
        spec: the :class:`FeatureSpec` shared with the measurements.
        k: neighbours.
        chunk: points synthesized at once (memory bound).
    """

    name = "kNN-CSI"

    def __init__(self, db: FingerprintDB, spec: FeatureSpec, *, k: int = 4,
                 chunk: int = 512) -> None:
        self.spec, self.k = spec, int(k)
        self.free = db.free_indices
        self.pos = db.points[self.free]
        rx = _robot_name(db, spec)
        freqs = spec.knn_frequencies
        self.features = []
        for a, ap in enumerate(db.ap_names):
            tx_arr = spec.arrays[ap]
            out = np.empty((len(self.free), len(freqs), tx_arr.num_ant), np.float32)
            for s in range(0, len(self.free), chunk):
                for j, i in enumerate(self.free[s:s + chunk]):
                    n = int(db.num_paths[i, a])
                    h = csi_from_paths(db.a[i, a, :n], db.lengths[i, a, :n] / 299_792_458.0,
                                       db.frequency_hz, freqs, spec.arrays[rx], tx_arr,
                                       theta_r=db.theta_r[i, a, :n], phi_r=db.phi_r[i, a, :n],
                                       theta_t=db.theta_t[i, a, :n], phi_t=db.phi_t[i, a, :n])
                    out[s + j] = to_db(np.mean(np.abs(h) ** 2, axis=1))
            self.features.append(out.reshape(len(self.free), -1))

    def __call__(self, obs: Observation) -> np.ndarray:
        d = np.zeros(len(self.pos))
        for f, m in zip(self.features, obs.csi_db):
            m = np.asarray(m, np.float32).reshape(-1)
            d += np.sum((f - m) ** 2, axis=1) / f.shape[1]
        return _weighted_knn(d, self.pos, self.k)


class PdpMatch:
    """Weighted kNN on the PDP in dB (see the module doc)."""

    name = "PDP"

    def __init__(self, db: FingerprintDB, spec: FeatureSpec, *, k: int = 4,
                 chunk: int = 2048) -> None:
        self.spec, self.k = spec, int(k)
        self.free = db.free_indices
        self.pos = db.points[self.free]
        feats = []
        for s in range(0, len(self.free), chunk):
            idx = self.free[s:s + chunk]
            feats.append(to_db(pdp_from_paths(db.lengths[idx], db.power[idx], spec.pdp_bins_m,
                                           spec.grid)).astype(np.float32))
        self.features = np.concatenate(feats)  # [F, A, B]

    def __call__(self, obs: Observation) -> np.ndarray:
        m = np.asarray(obs.pdp_db, np.float32)
        d = np.sum(np.mean((self.features - m[None]) ** 2, axis=2), axis=1)
        return _weighted_knn(d, self.pos, self.k)


def _robot_name(db: FingerprintDB, spec: FeatureSpec) -> str:
    rx = [n for n in spec.arrays if n not in db.ap_names]
    if not rx:
        raise ValueError("no receiver array in the feature spec")
    return rx[0]


def make_localizers(db: FingerprintDB, spec: FeatureSpec, *, mca: dict | None = None,
                    knn_k: int = 4, pdp_k: int = 4) -> dict:
    """``{"MCA": MCA, "MCA-angles": MCAAngles, "LOS-fix": LosFix, "kNN-CSI": KnnCsi,
    "PDP": PdpMatch}`` over ``db`` (``mca`` options go to both MCAs, ``cluster_m``
    to delay-only MCA only; ``LOS-fix`` only if an AP has more than one antenna)."""
    opts = dict(mca or {})
    ang = {k: v for k, v in opts.items() if k in ("eps", "k", "num_paths", "num_measured",
                                                   "angle_weight_m")}
    opts.pop("angle_weight_m", None)
    locs = {"MCA": MCA(db, **opts), "MCA-angles": MCAAngles(db, spec, **ang)}
    if any(spec.arrays[n].num_ant > 1 for n in db.ap_names):
        locs["LOS-fix"] = LosFix(db, spec)
    locs.update({"kNN-CSI": KnnCsi(db, spec, k=knn_k), "PDP": PdpMatch(db, spec, k=pdp_k)})
    return locs


#: Localizers by name, with the observation features each needs
#: (:func:`~isac_twin.localization.measurements.observe_pilots` ``features``).
METHODS = {"MCA": ("mdp",), "MCA-angles": ("mdp_fallback", "dirs"), "LOS-fix": ("dirs",),
           "PDP": ("pdp",), "kNN-CSI": ("csi",)}


def make_localizer(method: str, db: FingerprintDB, spec: FeatureSpec, *,
                   num_paths: int = 9, mca: dict | None = None):
    """One localizer by name (a key of :data:`METHODS`) over ``db``.

    Raises:
        ValueError: unknown method (the message lists the known ones).
    """
    if method == "MCA":
        return MCA(db, **{"num_paths": num_paths, **(mca or {})})
    if method == "MCA-angles":
        return MCAAngles(db, spec, num_paths=num_paths)
    if method == "LOS-fix":
        return LosFix(db, spec)
    if method == "PDP":
        return PdpMatch(db, spec)
    if method == "kNN-CSI":
        return KnnCsi(db, spec)
    raise ValueError(f"method: expected one of {', '.join(map(repr, METHODS))}, "
                     f"got {method!r}")


def observe_database_point(db: FingerprintDB, i: int, spec: FeatureSpec,
                           num_paths: int = 9) -> Observation:
    """The tracer-mode observation of database point ``i`` from its stored paths
    (robot array at yaw 0, as the database features): a noise-free check."""
    A = len(db.ap_names)
    rx = _robot_name(db, spec)
    lengths = np.full((A, num_paths), np.nan)
    powers = np.zeros((A, num_paths))
    csi, pdp, paths = [], [], []
    for a, ap in enumerate(db.ap_names):
        n = int(db.num_paths[i, a])
        j = min(n, num_paths)
        lengths[a, :j], powers[a, :j] = db.lengths[i, a, :j], db.power[i, a, :j]
        h = csi_from_paths(db.a[i, a, :n], db.lengths[i, a, :n] / 299_792_458.0,
                           db.frequency_hz, spec.knn_frequencies, spec.arrays[rx],
                           spec.arrays[ap], theta_r=db.theta_r[i, a, :n],
                           phi_r=db.phi_r[i, a, :n], theta_t=db.theta_t[i, a, :n],
                           phi_t=db.phi_t[i, a, :n])
        csi.append(to_db(np.mean(np.abs(h) ** 2, axis=1)))
        pdp.append(to_db(pdp_from_paths(db.lengths[i, a, :n], db.power[i, a, :n],
                                        spec.pdp_bins_m, spec.grid)))
        paths.append(DelayDirectionProfile(db.lengths[i, a, :j].astype(float),
                                           r_hat(db.theta_t[i, a, :j], db.phi_t[i, a, :j]),
                                           db.power[i, a, :j].astype(float))
                     if spec.arrays[ap].num_ant > 1 else None)
    return Observation(lengths, powers, csi, np.array(pdp), paths)
