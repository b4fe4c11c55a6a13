"""Multi-target tracker: constant-velocity Kalman filters in x, y.

State ``[x, y, vx, vy]`` (m, m/s); measurements ``[x, y]`` (m) from
geolocated detections. Per update: predict all tracks by ``dt``; gate
detections by the Mahalanobis distance of the innovation
(``chi2(2)`` quantile, default 99.9 %); associate by global nearest
neighbour (Hungarian assignment on the gated distances); update the
assigned tracks; start a tentative track from every unassigned detection.
Track management: a tentative track is *confirmed* after ``confirm_hits``
hits within its first ``confirm_window`` updates, else dropped; any track
is deleted after ``max_misses`` consecutive misses.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

__all__ = ["Track", "KalmanTracker"]


@dataclass
class Track:
    """One track.

    Attributes:
        id: unique integer id.
        x: state ``[x, y, vx, vy]`` (m, m/s).
        P: covariance ``[4, 4]``.
        hits, misses: associated updates / consecutive misses.
        age: updates since birth.
        confirmed: passed the confirmation test.
    """

    id: int
    x: np.ndarray
    P: np.ndarray
    hits: int = 1
    misses: int = 0
    age: int = 1
    confirmed: bool = False
    history: list = field(default_factory=list, repr=False)

    @property
    def position(self) -> np.ndarray:
        """``[x, y]`` (m)."""
        return self.x[:2].copy()

    @property
    def velocity(self) -> np.ndarray:
        """``[vx, vy]`` (m/s)."""
        return self.x[2:].copy()


class KalmanTracker:
    """Constant-velocity multi-target tracker.

    Args:
        meas_std_m: measurement noise std per axis [m].
        accel_std: white-acceleration process noise std [m/s^2].
        gate: Mahalanobis gate (squared distance) on the innovation.
        confirm_hits, confirm_window, max_misses: track management.
        init_speed_std: initial velocity std [m/s].
    """

    def __init__(self, meas_std_m: float = 0.25, accel_std: float = 0.3,
                 gate: float = 13.8, confirm_hits: int = 3, confirm_window: int = 5,
                 max_misses: int = 5, init_speed_std: float = 0.5) -> None:
        self.R = np.eye(2) * float(meas_std_m) ** 2
        self.q = float(accel_std) ** 2
        self.gate = float(gate)
        self.confirm_hits, self.confirm_window = int(confirm_hits), int(confirm_window)
        self.max_misses = int(max_misses)
        self.v0 = float(init_speed_std)
        self.tracks: list[Track] = []
        self._ids = itertools.count(1)
        self.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])

    def _predict(self, dt: float) -> None:
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        g = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        q = g @ g.T * self.q
        for t in self.tracks:
            t.x = f @ t.x
            t.P = f @ t.P @ f.T + q

    def update(self, measurements, dt: float) -> list[Track]:
        """One tracker cycle.

        Args:
            measurements: ``[M, 2]`` positions (m) of this step's detections.
            dt: time since the last update [s].

        Returns:
            the confirmed tracks.
        """
        z = np.asarray(measurements, float).reshape(-1, 2)
        self._predict(float(dt))
        n, m = len(self.tracks), len(z)
        assigned_t, assigned_m = set(), set()
        if n and m:
            cost = np.full((n, m), 1e6)
            for i, t in enumerate(self.tracks):
                s = self.H @ t.P @ self.H.T + self.R
                si = np.linalg.inv(s)
                nu = z - t.x[:2]
                d2 = np.einsum("mi,ij,mj->m", nu, si, nu)
                cost[i] = np.where(d2 <= self.gate, d2, 1e6)
            rows, cols = scipy.optimize.linear_sum_assignment(cost)
            for i, j in zip(rows, cols):
                if cost[i, j] >= 1e6:
                    continue
                t = self.tracks[i]
                s = self.H @ t.P @ self.H.T + self.R
                k = t.P @ self.H.T @ np.linalg.inv(s)
                t.x = t.x + k @ (z[j] - t.x[:2])
                t.P = (np.eye(4) - k @ self.H) @ t.P
                t.hits += 1
                t.misses = 0
                assigned_t.add(i)
                assigned_m.add(j)
        keep = []
        for i, t in enumerate(self.tracks):
            if i not in assigned_t:
                t.misses += 1
            t.age += 1
            if not t.confirmed and t.hits >= self.confirm_hits:
                t.confirmed = True
            if t.misses > self.max_misses:
                continue
            if not t.confirmed and t.age >= self.confirm_window and t.hits < self.confirm_hits:
                continue
            t.history.append(t.x[:2].copy())
            keep.append(t)
        for j in range(m):
            if j in assigned_m:
                continue
            p = np.diag([self.R[0, 0], self.R[1, 1], self.v0 ** 2, self.v0 ** 2])
            keep.append(Track(id=next(self._ids), x=np.r_[z[j], 0.0, 0.0], P=p))
        self.tracks = keep
        return self.confirmed

    @property
    def confirmed(self) -> list[Track]:
        """Confirmed tracks."""
        return [t for t in self.tracks if t.confirmed]
