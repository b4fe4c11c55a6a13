"""Fused robot pose: an EKF over odometry with gated RF position fixes.

State ``x = [x, y, yaw]`` (m, m, rad) of the robot base in the map frame,
covariance ``P [3, 3]``. The way a robot runs it:

* **predict** with each new odometry pose: the increment in the previous
  odometry body frame, ``ds = R(-yaw_odo) (p_odo - p_odo_prev)`` and
  ``dyaw``, is applied in the filter's frame,
  ``x_xy += R(yaw) ds``, ``yaw += dyaw``; process noise grows with the motion
  (``odom_std``: metres per metre travelled, radians per radian turned, plus
  radians per metre for the heading drift of driving straight);
* **update** with an RF fix of the antenna position ``z = [x, y]`` (m): the
  antenna sits at the body offset ``o`` (m), so ``h(x) = x_xy + R(yaw) o_xy``;
  the fix is accepted only if its squared Mahalanobis distance
  ``nu^T S^-1 nu`` is at most ``gate_chi2`` (chi-square, 2 degrees of freedom:
  9.21 keeps 99 % of good fixes), else it is counted in ``rejected``;
* **re-acquisition** (an overconfident state that drifted would gate out
  every good fix from then on): the innovations of the last
  ``reacquire_window`` fixes, accepted or not, are kept, moved with every
  correction an accepted fix makes (all against the current
  odometry-propagated track). When a fix is rejected, at least
  ``reacquire_after`` of the kept ones were rejected, and their median ``m``
  fails the chi-square gate with the median's own covariance,
  ``m^T (H P H^T + pi/2 R / n)^-1 m > gate_chi2`` (n kept fixes), the track
  is off: the position covariance is grown by ``m m^T`` and the filter is
  updated with ``h(x) + m`` (fix covariance ``R``: neighbouring fixes share
  their bias, so their number does not shrink it). A jump is never larger
  than what most recent fixes say; after a large slip the window fills with
  the new offset and a second re-acquisition finishes the correction. The median over the
  whole window, not the rejected fixes alone, decides: scattered outliers
  (fixes 20-30 cm off on alternating sides) and a short run of fixes biased
  one way while most fixes agree with the track (MCA-angles does both in a
  lap of the lab) never move the state; a drift that most fixes see does.
  (The earlier rule used the 5th consecutive rejected fix, whatever it was:
  in a lap it jumped onto a fix 30 cm off the truth.)
"""

from __future__ import annotations

import math

import numpy as np

from ..utils.geometry import wrap_angle

__all__ = ["PoseEKF"]


def _rot(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s], [s, c]])


class PoseEKF:
    """EKF over ``[x, y, yaw]`` with odometry prediction and gated position fixes.

    Args:
        pose: initial ``[x, y, yaw]`` (m, m, rad), e.g. the calibrated start.
        odometry: the odometry pose ``[x, y, yaw]`` at the same instant.
        initial_std: ``(m, rad)`` standard deviation of the initial pose.
        odom_std: ``(m/m, rad/rad, rad/m)``: translation noise per metre
            travelled, heading noise per radian turned, heading noise per metre.
        fix_std_m: standard deviation of one RF fix per axis, m.
        antenna_offset: ``[x, y]`` of the antenna in the body frame, m.
        gate_chi2: gate on the squared Mahalanobis distance of a fix.
        reacquire_after: rejected fixes among the last ``reacquire_window``
            needed before a re-acquisition is considered.
        reacquire_window: recent fixes (accepted or not) whose median
            innovation decides a re-acquisition.

    Raises:
        ValueError: non-finite poses, non-positive standard deviations or gate.
    """

    def __init__(self, pose, odometry, *, initial_std=(0.05, math.radians(2.0)),
                 odom_std=(0.05, 0.05, math.radians(1.0)), fix_std_m: float = 0.05,
                 antenna_offset=(0.0, 0.0), gate_chi2: float = 9.21,
                 reacquire_after: int = 5, reacquire_window: int = 16) -> None:
        self.x = self._pose("pose", pose)
        self._odo = self._pose("odometry", odometry)
        vals = {"initial_std": initial_std, "odom_std": odom_std, "fix_std_m": [fix_std_m],
                "gate_chi2": [gate_chi2]}
        for k, v in vals.items():
            if not np.all(np.isfinite(v)) or not np.all(np.asarray(v, float) > 0):
                raise ValueError(f"{k}: expected positive finite values, got {v!r}")
        self.P = np.diag([initial_std[0] ** 2, initial_std[0] ** 2, initial_std[1] ** 2])
        self.odom_std = tuple(float(v) for v in odom_std)
        self.R = np.eye(2) * float(fix_std_m) ** 2
        self.offset = np.asarray(antenna_offset, float).reshape(2)
        self.gate = float(gate_chi2)
        if int(reacquire_after) < 1:
            raise ValueError(f"reacquire_after: expected >= 1, got {reacquire_after!r}")
        self.reacquire_after = int(reacquire_after)
        if int(reacquire_window) < self.reacquire_after:
            raise ValueError(f"reacquire_window: expected >= reacquire_after "
                             f"({self.reacquire_after}), got {reacquire_window!r}")
        self.reacquire_window = int(reacquire_window)
        self._fixes = 0  # fixes seen (update calls)
        # the last ``reacquire_window`` fixes: (fix index, innovation against the
        # current track, rejected?)
        self._recent: list[tuple[int, np.ndarray, bool]] = []
        self.accepted = 0  #: fixes used (a re-acquisition counts as one)
        self.rejected = 0  #: fixes refused by the gate
        self.reacquired = 0  #: re-acquisitions on agreeing rejected fixes

    @staticmethod
    def _pose(name, v) -> np.ndarray:
        v = np.asarray(v, float).reshape(-1)
        if v.shape != (3,) or not np.isfinite(v).all():
            raise ValueError(f"{name}: expected [x, y, yaw] (3 finite numbers), got {v!r}")
        return v.copy()

    @property
    def pose(self) -> np.ndarray:
        """``[x, y, yaw]`` estimate (m, m, rad)."""
        return self.x.copy()

    @property
    def antenna_xy(self) -> np.ndarray:
        """``[x, y]`` estimate of the antenna, m."""
        return self.x[:2] + _rot(self.x[2]) @ self.offset

    def predict(self, odometry) -> None:
        """Propagate with a new odometry pose ``[x, y, yaw]``."""
        odo = self._pose("odometry", odometry)
        ds = _rot(-self._odo[2]) @ (odo[:2] - self._odo[:2])  # body-frame increment
        dyaw = wrap_angle(odo[2] - self._odo[2])
        self._odo = odo
        t = self.x[2]
        step = _rot(t) @ ds
        # d(step)/d(yaw)
        dstep = np.array([-math.sin(t) * ds[0] - math.cos(t) * ds[1],
                          math.cos(t) * ds[0] - math.sin(t) * ds[1]])
        F = np.eye(3)
        F[:2, 2] = dstep
        self.x[:2] += step
        self.x[2] = wrap_angle(t + dyaw)
        dist = float(np.hypot(*ds))
        a_t, a_r, a_d = self.odom_std
        var_t = (a_t * dist) ** 2 + 1e-8
        var_r = (a_r * abs(dyaw)) ** 2 + (a_d * dist) ** 2 + 1e-10
        G = _rot(t)
        Q = np.zeros((3, 3))
        Q[:2, :2] = G @ (np.eye(2) * var_t) @ G.T
        Q[2, 2] = var_r
        self.P = F @ self.P @ F.T + Q

    def update(self, fix_xy) -> bool:
        """Use an RF fix ``[x, y]`` (m) of the antenna; returns whether the gate
        accepted it."""
        z = np.asarray(fix_xy, float).reshape(-1)[:2]
        if z.shape != (2,) or not np.isfinite(z).all():
            raise ValueError(f"fix: expected [x, y] (2 finite numbers, m), got {fix_xy!r}")
        t = self.x[2]
        h = self.antenna_xy
        H = np.zeros((2, 3))
        H[:, :2] = np.eye(2)
        dr = np.array([[-math.sin(t), -math.cos(t)], [math.cos(t), -math.sin(t)]])  # dR/dyaw
        H[:, 2] = dr @ self.offset
        nu = z - h
        S = H @ self.P @ H.T + self.R
        self._fixes += 1
        self._recent = [r for r in self._recent if r[0] > self._fixes - self.reacquire_window]
        out = float(nu @ np.linalg.solve(S, nu)) > self.gate
        self._recent.append((self._fixes, nu, out))
        if out:
            self.rejected += 1
            m = self._consensus(H @ self.P @ H.T)
            if m is None:
                return False
            self.rejected -= 1  # used after all
            self.reacquired += 1
            self.P[:2, :2] += np.outer(m, m)  # drifted: re-acquire on the median innovation
            nu = m
            S = H @ self.P @ H.T + self.R
            self._recent = []
        K = self.P @ H.T @ np.linalg.inv(S)
        before = self.antenna_xy
        self.x = self.x + K @ nu
        self.x[2] = wrap_angle(self.x[2])
        moved = self.antenna_xy - before  # kept innovations are against the moved track
        self._recent = [(i, v - moved, r) for i, v, r in self._recent]
        ikh = np.eye(3) - K @ H
        self.P = ikh @ self.P @ ikh.T + K @ self.R @ K.T  # Joseph form
        self.accepted += 1
        return True

    def _consensus(self, p_h: np.ndarray) -> np.ndarray | None:
        """The median innovation of the recent fixes when it says the track is off
        (see the module doc; ``p_h`` = ``H P H^T``), else None."""
        n = len(self._recent)
        if sum(r for _, _, r in self._recent) < self.reacquire_after:
            return None
        med = np.median(np.array([v for _, v, _ in self._recent]), axis=0)
        # variance of a median of n Gaussian samples: pi / 2 R / n
        s = p_h + 0.5 * math.pi * self.R / n
        if float(med @ np.linalg.solve(s, med)) <= self.gate:
            return None
        return med
