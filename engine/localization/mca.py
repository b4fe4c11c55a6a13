"""Multipath component analysis (MCA): fingerprint localization with delay profiles.

After Zayets and Steinbach, "Robust WiFi-based indoor localization using
multipath component analysis", IPIN 2017 (see
``shared/reference/localization.md``). A fingerprint is, per access point, an
unordered set of path lengths ``d = c * tau`` (m). The score of a database
point with lengths ``f_1..f_L`` against measured lengths ``d_1..d_J`` is

    sum over APs, sum over j of (eps - |d_j - f_nearest(j)|)^2  if that distance < eps

and the best-scoring points, averaged with their scores as weights (k-best),
give the estimate.

The query is exact but avoids touching all ``P x A x J x L`` distances: an
upper-bound table over length bins (one row of ``P`` scores per AP and bin)
scores every point with ``A x J`` row additions, then exact scores are
computed only for candidates in upper-bound order until no remaining
candidate can beat the current k-th best (branch and bound).

With departure directions the length-only bins are a loose bound (a point
whose lengths match but whose directions do not scores far below it); the
measured paths that carry a direction are then scored exactly for every
point instead, from the database's (point, path) pairs sorted by length:
only the pairs within ``eps`` in length can score, a contiguous slice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LocationEstimate:
    """Result of one query.

    Attributes:
        position: ``[3]`` weighted estimate, m.
        best_indices: ``[k]`` database indices, best first.
        best_scores: ``[k]`` their MCA scores (m^2), descending.
        candidates_scored: how many points needed an exact score.
    """

    position: np.ndarray
    best_indices: np.ndarray
    best_scores: np.ndarray
    candidates_scored: int


def _pad_sorted(db: np.ndarray) -> np.ndarray:
    """Sort each fingerprint's lengths, NaN (no path) last."""
    db = np.asarray(db, dtype=np.float64)
    return np.sort(np.where(np.isfinite(db), db, np.inf), axis=-1)


def _sort_order(db: np.ndarray) -> np.ndarray:
    """The permutation ``[P, A, L]`` :func:`_pad_sorted` applies."""
    db = np.asarray(db, dtype=np.float64)
    return np.argsort(np.where(np.isfinite(db), db, np.inf), axis=-1, kind="stable")


class MCALocalizer:
    """MCA over a whole fingerprint database, vectorised.

    Args:
        positions: ``[P, 3]`` database positions, m.
        lengths: ``[P, A, L]`` path lengths ``c * tau`` per point and access
            point, m; NaN or inf pads missing paths.
        eps: matching radius, m (0.5 in the published comparison).
        k: number of best points averaged (k = 1 is nearest neighbour).
        bin_m: width of the upper-bound table's length bins, m.
        directions: optional ``[P, A, L, 3]`` departure directions at the APs
            (unit vectors, world axes; NaN where unknown). With them, a
            measured path that carries a direction is matched by the distance
            ``sqrt(dd^2 + (angle_weight_m |k - k_db|)^2)`` (``dd`` the length
            difference, ``|k - k_db|`` the chord between the unit vectors)
            instead of ``|dd|``; paths or APs without a direction (single
            antennas) keep ``|dd|``. The length-only bound table stays an
            upper bound (the combined distance is never shorter).
        angle_weight_m: metres per unit of direction chord (about the
            AP-robot distance turns an angle error into a lateral offset).
        exact_paths, exact_min_weight: with directions, up to ``exact_paths``
            measured paths per AP that carry a direction and a score weight
            of at least ``exact_min_weight`` (the heaviest first) are scored
            exactly over all points for the bound (module doc); the others
            keep the length-only table. Only the query's speed depends on them.

    Raises:
        ValueError: inconsistent shapes, non-finite positions, eps or k out of range.
    """

    def __init__(self, positions, lengths, *, eps: float = 0.5, k: int = 4,
                 bin_m: float = 0.05, directions=None, angle_weight_m: float = 3.0,
                 exact_paths: int = 3, exact_min_weight: float = 0.3) -> None:
        positions = np.asarray(positions, dtype=np.float64)
        raw = np.asarray(lengths, dtype=np.float64)
        lengths = _pad_sorted(raw)
        self.directions = None
        if directions is not None:
            directions = np.asarray(directions, dtype=np.float64)
            if directions.shape != raw.shape + (3,):
                raise ValueError(f"directions: expected shape {list(raw.shape) + [3]} "
                                 f"([P, A, L, 3] unit vectors), got {list(directions.shape)}")
            order = _sort_order(raw)
            self.directions = np.take_along_axis(directions, order[..., None], axis=2)
        if not angle_weight_m > 0:
            raise ValueError(f"angle_weight_m: expected > 0 m, got {angle_weight_m}")
        self.angle_weight_m = float(angle_weight_m)
        if not (exact_paths >= 0 and exact_min_weight >= 0):
            raise ValueError(f"exact_paths, exact_min_weight: expected >= 0, got "
                             f"{exact_paths}, {exact_min_weight}")
        self.exact_paths, self.exact_min_weight = int(exact_paths), float(exact_min_weight)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions: expected shape [P, 3], got {positions.shape}")
        if lengths.ndim != 3 or lengths.shape[0] != positions.shape[0]:
            raise ValueError(f"lengths: expected shape [P={positions.shape[0]}, A, L], "
                             f"got {lengths.shape}")
        if not np.isfinite(positions).all():
            raise ValueError("positions: contains NaN or inf")
        if not eps > 0:
            raise ValueError(f"eps: expected a positive radius in m, got {eps}")
        if not 1 <= k <= len(positions):
            raise ValueError(f"k: expected 1..{len(positions)}, got {k}")
        self.positions, self.lengths = positions, lengths
        self.eps, self.k, self.bin_m = float(eps), int(k), float(bin_m)
        self._build_table()
        self._build_pairs()

    @property
    def num_aps(self) -> int:
        return self.lengths.shape[1]

    def _build_table(self) -> None:
        P, A, L = self.lengths.shape
        finite = self.lengths[np.isfinite(self.lengths)]
        top = (finite.max() if finite.size else 0.0) + self.eps + self.bin_m
        nb = int(np.ceil(top / self.bin_m)) + 1
        # Upper bound per (AP, bin, point): the best score any length inside the
        # bin can get, from the nearest database length minus half a bin.
        table = np.zeros((A, nb, P), dtype=np.float32)
        reach = int(np.ceil(self.eps / self.bin_m)) + 1
        centres = (np.arange(nb) + 0.5) * self.bin_m
        cols = np.arange(P)
        for a in range(A):
            for l in range(L):
                f = self.lengths[:, a, l]
                ok = np.isfinite(f)
                if not ok.any():
                    continue
                b0 = np.floor(f[ok] / self.bin_m).astype(np.int64)
                for off in range(-reach, reach + 1):
                    b = b0 + off
                    inb = (b >= 0) & (b < nb)
                    bb, pp = b[inb], cols[ok][inb]
                    d = np.maximum(np.abs(centres[bb] - f[ok][inb]) - self.bin_m / 2, 0.0)
                    s = np.where(d < self.eps, (self.eps - d) ** 2, 0.0).astype(np.float32)
                    np.maximum.at(table[a], (bb, pp), s)
        self._table, self._nbins = table, nb

    def _build_pairs(self) -> None:
        """Per AP with directions, its (point, path) pairs sorted by length:
        lengths ``[n]`` m, points ``[n]``, directions ``[n, 3]`` (``None``
        for APs without any direction)."""
        self._pairs = [None] * self.num_aps
        if self.directions is None:
            return
        for a in range(self.num_aps):
            f = self.lengths[:, a]  # [P, L]
            k = self.directions[:, a]  # [P, L, 3]
            if not np.isfinite(k).all(axis=-1).any():
                continue  # a single antenna: length only, the table is exact enough
            ok = np.isfinite(f)
            pt = np.broadcast_to(np.arange(len(f))[:, None], f.shape)[ok]
            order = np.argsort(f[ok], kind="stable")
            kk = k[ok][order]
            has = np.isfinite(kk).all(axis=-1)  # no direction: matched by length only
            kk = np.ascontiguousarray(np.where(has[:, None], kk, 0.0))
            self._pairs[a] = (np.ascontiguousarray(f[ok][order]), pt[order].astype(np.intp),
                              kk, np.sum(kk * kk, axis=1), has)

    def _path_scores(self, a: int, length: float, direction: np.ndarray) -> np.ndarray:
        """Exact score ``[P]`` of one measured path (``length`` m, unit
        ``direction`` [3]) at AP ``a`` against every point (unweighted): the
        ``(eps - d)^2`` of the nearest database path, 0 beyond ``eps``."""
        f, pt, k, k2, has = self._pairs[a]
        lo = np.searchsorted(f, length - self.eps, side="right")
        hi = np.searchsorted(f, length + self.eps, side="left")
        out = np.zeros(len(self.positions))
        if hi <= lo:
            return out
        # |k - k_db|^2 = |k|^2 + |k_db|^2 - 2 k . k_db (a bound: its rounding,
        # ~1e-16 in the chord^2, is far inside the branch and bound's slack)
        chord2 = k2[lo:hi] + float(direction @ direction) - 2.0 * (k[lo:hi] @ direction)
        chord2 = np.where(has[lo:hi], np.maximum(chord2, 0.0), 0.0)
        d2 = (f[lo:hi] - length) ** 2 + self.angle_weight_m ** 2 * chord2
        near = np.flatnonzero(d2 < self.eps ** 2)
        np.maximum.at(out, pt[lo + near], (self.eps - np.sqrt(d2[near])) ** 2)
        return out

    def exact_scores(self, measured: np.ndarray, idx: np.ndarray,
                     measured_directions: np.ndarray | None = None,
                     weights: np.ndarray | None = None) -> np.ndarray:
        """Exact MCA scores of database points ``idx`` ``[M]`` -> ``[M]`` (m^2).

        ``measured`` is ``[A, J]`` lengths in m, NaN-padded;
        ``measured_directions`` optional ``[A, J, 3]`` unit vectors (NaN: none);
        ``weights`` optional ``[A, J]`` per measured path.
        """
        db = self.lengths[idx]  # [M, A, L]
        diff = np.abs(measured[None, :, :, None] - db[:, :, None, :])  # [M, A, J, L]
        if measured_directions is not None and self.directions is not None:
            kd = self.directions[idx]  # [M, A, L, 3]
            chord = np.linalg.norm(measured_directions[None, :, :, None, :]
                                   - kd[:, :, None, :, :], axis=-1)  # [M, A, J, L]
            # no direction on either side -> length only
            chord = np.where(np.isfinite(chord), chord, 0.0)
            diff = np.hypot(diff, self.angle_weight_m * chord)
        near = np.min(diff, axis=-1)  # [M, A, J]
        s = np.where(near < self.eps, (self.eps - near) ** 2, 0.0)
        if weights is not None:
            s = s * weights[None]
        return np.nansum(s, axis=(1, 2))

    def _check_measured(self, measured) -> np.ndarray:
        m = np.asarray(measured, dtype=np.float64)
        if m.ndim == 1 and self.num_aps == 1:
            m = m[None]
        if m.ndim != 2 or m.shape[0] != self.num_aps:
            raise ValueError(f"measured: expected [A={self.num_aps}, J] path lengths in m, "
                             f"got shape {m.shape}")
        if np.isinf(m).any() or (m[np.isfinite(m)] < 0).any():
            raise ValueError("measured: path lengths must be finite and >= 0 (NaN pads)")
        return m

    def __call__(self, measured, directions=None, weights=None) -> LocationEstimate:
        """Localize one measurement.

        Args:
            measured: ``[A, J]`` measured path lengths per AP, m (NaN pads).
            directions: optional ``[A, J, 3]`` departure directions of the
                measured paths (unit vectors, world axes; NaN: unknown).
            weights: optional ``[A, J]`` weights in ``[0, 1]`` of the measured
                paths' scores (default 1, the published MCA).

        Returns:
            The k-best weighted estimate (all-zero scores fall back to an
            unweighted mean of the k candidates with the highest bound).
        """
        m = self._check_measured(measured)
        kdir = None
        if directions is not None:
            kdir = np.asarray(directions, dtype=np.float64)
            if kdir.shape != m.shape + (3,):
                raise ValueError(f"directions: expected shape {list(m.shape) + [3]} "
                                 f"([A, J, 3] unit vectors), got {list(kdir.shape)}")
        wts = None
        if weights is not None:
            wts = np.asarray(weights, dtype=np.float64)
            if wts.shape != m.shape or not np.all((wts >= 0) & (wts <= 1)):
                raise ValueError(f"weights: expected shape {list(m.shape)} with values in "
                                 f"[0, 1], got shape {list(wts.shape)}")
        ub = np.zeros(self._table.shape[2], dtype=np.float32)
        exact = None  # exact scores of the paths with a direction (see the module doc)
        for a in range(self.num_aps):
            ok = np.isfinite(m[a])
            w_all = np.ones(m.shape[1]) if wts is None else wts[a]
            if kdir is not None and self._pairs[a] is not None:
                has = np.flatnonzero(ok & np.isfinite(kdir[a]).all(axis=-1)
                                     & (w_all >= self.exact_min_weight))
                has = has[np.argsort(-w_all[has], kind="stable")[:self.exact_paths]]
                for j in has:
                    s_j = self._path_scores(a, m[a, j], kdir[a, j])
                    exact = w_all[j] * s_j if exact is None else exact + w_all[j] * s_j
                ok[has] = False
            bins = np.floor(m[a][ok] / self.bin_m).astype(np.int64)
            w = w_all[ok].astype(np.float32)
            inb = (bins >= 0) & (bins < self._nbins)
            if inb.any():
                ub += w[inb] @ self._table[a, bins[inb]]
        if exact is not None:
            ub = ub + exact
        k = self.k
        chunk = max(64, 4 * k)
        n = len(ub)
        if chunk < n:
            # Fast path: the top `chunk` bounds by partial selection (no full sort);
            # usually the k-th exact score already beats every other bound.
            part = np.argpartition(-ub, chunk)
            first = part[:chunk]
            s = self.exact_scores(m, first, kdir, wts)
            keep = np.argsort(-s, kind="stable")[:k]
            if ub[part[chunk]] <= s[keep[-1]] - 1e-6:
                return self._estimate(first[keep], s[keep], chunk)
        order = np.argsort(-ub, kind="stable")
        best_i = np.empty(0, dtype=np.int64)
        best_s = np.empty(0)
        start = 0
        while start < len(order):
            idx = order[start:start + chunk]
            s = self.exact_scores(m, idx, kdir, wts)
            best_i = np.concatenate([best_i, idx])
            best_s = np.concatenate([best_s, s])
            keep = np.argsort(-best_s, kind="stable")[:k]
            best_i, best_s = best_i[keep], best_s[keep]
            start += chunk
            # Float32 table: allow a hair of slack before declaring the bound met.
            if len(best_s) == k and start < len(order) and ub[order[start]] <= best_s[-1] - 1e-6:
                break
            chunk *= 2
        return self._estimate(best_i, best_s, min(start, len(order)))

    def _estimate(self, best_i, best_s, scored: int) -> LocationEstimate:
        w = best_s
        if w.sum() > 0:
            pos = (w[:, None] * self.positions[best_i]).sum(0) / w.sum()
        else:
            pos = self.positions[best_i].mean(0)
        return LocationEstimate(position=pos, best_indices=best_i, best_scores=best_s,
                                candidates_scored=int(scored))
