r"""Joint delay-direction estimation at a multi-antenna access point from comb pilots.

The PHY's comb pilots (:class:`~isac_twin.phy.estimation.PilotPattern`, ``"comb"``)
give every transmit antenna (port ``p``) its own comb: port ``p`` sits on the
allocated subcarriers ``p, p + S, p + 2S, ...`` (stride ``S >= P``). The LS
estimates at the combs, ``csi[m, r, p]`` (comb index ``m``, receive antenna
``r``, port ``p``), follow

    ``csi[m, r, p] = sum_l c_{l,r} a_p(k_l) exp(-j 2 pi (m S delta_f + o_p) tau_l)``

with ``o_p`` the port's comb offset [Hz] (``p delta_f`` for the PHY's combs) and
``a_p(k) = exp(+j 2 pi pos_p . k)`` the AP array's steering vector
(:class:`~isac_twin.phy.arrays.PlanarArray`; ``k`` is the departure direction,
world frame, pointing away from the AP). :class:`DelayDirectionEstimator`
returns, per component, the path length ``c tau`` [m], the departure direction
``k`` [3] (unit vector, world axes) and the power ``mean_r |c_{l,r}|^2``:

1. delays: :class:`~isac_twin.phy.estimation.MdpEstimator` (TLS-ESPRIT,
   robust order, least squares on the chosen order) on the comb, every ``(r, p)`` a snapshot (a
   port's comb offset is a constant phase per snapshot there);
2. per delay, the amplitudes over the ports, with the comb offset
   ``exp(-j 2 pi o_p tau_l)`` removed, form a spatial snapshot of the array;
   its direction is the peak of a zero-padded 2-D DFT over columns x rows,
   refined by Newton steps (analytic derivatives) on ``(u, v)`` (the direction cosines along the
   array's local y and z axes);
3. a delay whose spatial snapshot keeps more than ``split_fraction`` of its
   energy outside the first direction holds a second path (a cluster the
   band cannot split in delay): its direction is found on the residual;
4. all ``(delay, direction)`` components are re-fitted jointly to every
   comb sample (amplitudes per receive antenna), which gives the powers.

A planar array sees only ``u`` and ``v``; the component along its boresight
(local +x) is taken positive (paths leave the AP's front, as for a
wall-mounted AP): ``k_local = [sqrt(1 - u^2 - v^2), u, v]``, ``k = R k_local``.
A single-column or single-row array resolves only one of ``u``, ``v``; the
other is returned as 0 (its direction cosines are then a cone's closest
point to boresight); a single antenna has no direction (use the MDP).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._checks import complex_array, positive_float, positive_int, real_array
from .arrays import PlanarArray, sionna_rotation
from .estimation import MdpEstimator
from .units import SPEED_OF_LIGHT

__all__ = ["DelayDirectionProfile", "DelayDirectionEstimator"]


@dataclass(frozen=True)
class DelayDirectionProfile:
    """Paths seen at a multi-antenna AP, strongest first.

    Attributes:
        distances_m: Path lengths ``c tau`` ``[L]`` [m].
        directions: Departure directions ``[L, 3]``: unit vectors, world
            axes, pointing away from the AP (Sionna's ``r_hat(theta_t, phi_t)``).
        powers: Powers ``[L]`` (``|c|^2`` per antenna pair, averaged over the
            receive antennas; units of ``|csi|^2``).
    """

    distances_m: np.ndarray
    directions: np.ndarray
    powers: np.ndarray

    def __len__(self) -> int:
        return int(self.distances_m.size)

    @property
    def zenith_rad(self) -> np.ndarray:
        """Departure zenith ``[L]`` [rad] (from +z)."""
        return np.arccos(np.clip(self.directions[:, 2], -1.0, 1.0))

    @property
    def azimuth_rad(self) -> np.ndarray:
        """Departure azimuth ``[L]`` [rad] (from +x towards +y)."""
        return np.arctan2(self.directions[:, 1], self.directions[:, 0])


class DelayDirectionEstimator:
    """Joint delay-direction estimator of one AP (see the module doc).

    Args:
        array: The AP's :class:`PlanarArray` (``P = rows * cols`` ports, port
            ``p`` on antenna ``p``).
        comb_spacing_hz: Spacing of one port's comb ``S delta_f`` [Hz].
        orientation: The AP array's ``[yaw, pitch, roll]`` [rad] (Sionna order).
        max_paths: Cap on the delays estimated (step 1).
        split_fraction: Spatial energy fraction left by one direction above
            which a delay gets a second direction (step 3); ``None``: never.
        max_distance_m: Drop delays beyond this path length (aliases of the
            comb, which repeat every ``c / (S delta_f)``).
        fft_size: Zero-padded DFT size per array axis for the initial search.

    Call: ``csi [M, Nr, P]`` (LS values at each port's comb, all ports' combs
    the same length ``M``), ``port_offsets_hz [P]`` (``o_p``: frequency of
    port ``p``'s first comb subcarrier minus port 0's) ->
    :class:`DelayDirectionProfile`.
    """

    def __init__(self, array: PlanarArray, comb_spacing_hz: float, *,
                 orientation=(0.0, 0.0, 0.0), max_paths: int = 9,
                 split_fraction: float | None = 0.3, max_distance_m: float | None = None,
                 fft_size: int = 64) -> None:
        if not isinstance(array, PlanarArray):
            raise ValueError("array must be a PlanarArray")
        if array.num_ant < 2:
            raise ValueError("a single antenna has no direction: use MdpEstimator")
        self.array = array
        self.df = positive_float("comb_spacing_hz", comb_spacing_hz)
        self.rot = sionna_rotation(orientation)
        self.max_paths = positive_int("max_paths", max_paths)
        if split_fraction is not None and not 0 < split_fraction < 1:
            raise ValueError(f"split_fraction must be in (0, 1) or None, got {split_fraction!r}")
        self.split_fraction = split_fraction
        self.fft_size = positive_int("fft_size", fft_size)
        self.mdp = MdpEstimator(self.df, max_paths=max_paths, max_distance_m=max_distance_m,
                                refine="final")
        pos = array.normalized_positions  # [P, 3] wavelengths, local axes
        self._y, self._z = pos[:, 1], pos[:, 2]
        self._rows, self._cols = array.num_rows, array.num_cols
        k = np.arange(self.fft_size)
        # zero-padded DFT over the columns (forward) and rows (inverse, unscaled)
        self._dft_cols = np.exp(-2j * np.pi * np.outer(k, np.arange(self._cols)) / self.fft_size)
        self._dft_rows = np.exp(2j * np.pi * np.outer(k, np.arange(self._rows)) / self.fft_size)

    # ------------------------------------------------------------ geometry

    def _steer(self, uv: np.ndarray) -> np.ndarray:
        """Steering vectors ``[L, P]`` for local direction cosines ``uv [L, 2]``."""
        return np.exp(2j * np.pi * (uv[:, :1] * self._y + uv[:, 1:] * self._z))

    def _world(self, uv: np.ndarray) -> np.ndarray:
        """World unit vectors ``[L, 3]`` from ``uv [L, 2]`` (front hemisphere)."""
        uv = np.asarray(uv, float)
        r = np.hypot(uv[:, 0], uv[:, 1])
        uv = uv / np.maximum(r, 1.0)[:, None]  # |(u, v)| <= 1
        x = np.sqrt(np.maximum(0.0, 1.0 - np.sum(uv ** 2, axis=1)))
        return np.stack([x, uv[:, 0], uv[:, 1]], axis=1) @ self.rot.T

    def _directions(self, x: np.ndarray) -> np.ndarray:
        """Direction cosines ``(u, v)`` ``[L, 2]`` maximising
        ``sum_r |a(u, v)^H x_r|^2`` for each of ``L`` spatial snapshots
        ``x [L, P, Nr]``: the peak of the beam power on a zero-padded
        ``fft_size``-point DFT grid per array axis (two small matrix products),
        then up to 8 Newton steps, all snapshots at once."""
        a = self.array
        n = self.fft_size
        nl, nr = x.shape[0], x.shape[2]
        # element i = c * rows + r sits at y = dh c + y0, z = -dv r + z0:
        # sum_c sum_r x exp(-j 2 pi (c iu - r iv) / n) on the n x n grid (iu, iv)
        g = x.reshape(nl, self._cols, self._rows * nr)
        spec = (self._dft_cols @ g).reshape(nl, n, self._rows, nr)  # over columns
        spec = np.swapaxes(spec, 2, 3) @ self._dft_rows.T  # [L, n, Nr, n]: over rows
        pw = np.sum(spec.real ** 2 + spec.imag ** 2, axis=2).reshape(nl, -1)
        ic, ir = np.unravel_index(np.argmax(pw, axis=1), (n, n))
        freq = np.fft.fftfreq(n)
        uv = np.zeros((nl, 2))
        if self._cols > 1:
            uv[:, 0] = freq[ic] / a.horizontal_spacing
        if self._rows > 1:
            uv[:, 1] = freq[ir] / a.vertical_spacing
        free = [i for i, m in enumerate((self._cols, self._rows)) if m > 1]

        coords = np.stack([self._y, self._z])  # [2, P] wavelengths
        cc = (coords[:, None, :] * coords[None, :, :]).reshape(4, -1)  # [4, P]
        active = np.ones(nl, bool)
        for _ in range(8):  # Newton on the beam power f = sum_r |a(u, v)^H x_r|^2
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            w = np.conj(self._steer(uv[idx]))[:, :, None] * x[idx]  # [l, P, Nr]
            b = w.sum(axis=1)  # [l, Nr]
            b1 = -2j * np.pi * (coords @ w)  # [l, 2, Nr]: d b / d(u, v)
            b2 = (-4 * np.pi ** 2 * (cc @ w)).reshape(-1, 2, 2, nr)  # [l, 2, 2, Nr]
            cb = np.conj(b)
            grad = 2 * np.real(cb[:, None, :] * b1).sum(axis=2)  # [l, 2]
            hess = 2 * np.real(b1 @ np.conj(np.swapaxes(b1, 1, 2))
                               + (cb[:, None, None, :] * b2).sum(axis=3))  # [l, 2, 2]
            step = np.zeros((idx.size, 2))
            with np.errstate(divide="ignore", invalid="ignore"):
                if len(free) == 2:
                    det = hess[:, 0, 0] * hess[:, 1, 1] - hess[:, 0, 1] * hess[:, 1, 0]
                    step[:, 0] = -(hess[:, 1, 1] * grad[:, 0] - hess[:, 0, 1] * grad[:, 1]) / det
                    step[:, 1] = -(hess[:, 0, 0] * grad[:, 1] - hess[:, 1, 0] * grad[:, 0]) / det
                elif len(free) == 1:
                    f = free[0]
                    step[:, f] = -grad[:, f] / hess[:, f, f]
            big = np.max(np.abs(step), axis=1)
            # singular, or not in the concave basin of the peak: keep what we have
            stop = ~np.isfinite(big) | (big > 0.05)
            go = idx[~stop]
            uv[go] += step[~stop]
            active[idx[stop]] = False
            active[go[big[~stop] < 1e-7]] = False
        return uv

    # ------------------------------------------------------------ estimation

    def __call__(self, csi, port_offsets_hz) -> DelayDirectionProfile:
        h = complex_array("csi", csi, ndim=3)
        m, nr, p = h.shape
        if p != self.array.num_ant:
            raise ValueError(f"csi must have P = {self.array.num_ant} ports on axis 2 "
                             f"(one per antenna), got {list(h.shape)}")
        off = real_array("port_offsets_hz", port_offsets_hz, shape=(p,))
        empty = DelayDirectionProfile(np.zeros(0), np.zeros((0, 3)), np.zeros(0))
        if not np.any(h):
            return empty
        fm = np.arange(m) * self.df
        mdp = self.mdp(h.reshape(m, nr * p), frequencies_hz=fm)
        if len(mdp) == 0:
            return empty
        tau = mdp.delays_s
        e = np.exp(-2j * np.pi * np.outer(fm, tau))  # [M, L]
        amp, *_ = np.linalg.lstsq(e, h.reshape(m, nr * p), rcond=None)
        amp = amp.reshape(len(tau), nr, p)
        # spatial snapshots [L, P, Nr], comb offsets removed
        xs = np.transpose(amp * np.exp(2j * np.pi * np.outer(tau, off))[:, None, :], (0, 2, 1))
        uv = self._directions(xs)
        split = np.zeros(len(tau), bool)
        if self.split_fraction is not None:
            s = self._steer(uv)  # [L, P]
            res = xs - s[:, :, None] * (np.einsum("lp,lpr->lr", np.conj(s), xs)[:, None, :] / p)
            e_res = np.sum(res.real ** 2 + res.imag ** 2, axis=(1, 2))
            e_all = np.sum(xs.real ** 2 + xs.imag ** 2, axis=(1, 2))
            split = e_res > self.split_fraction * e_all
        # components in delay order, a split delay's second direction right after it
        tau_c = np.repeat(tau, 1 + split)
        uv_c = np.repeat(uv, 1 + split, axis=0)
        if split.any():
            second = np.cumsum(1 + split)[split] - 1
            uv_c[second] = self._directions(res[split])
        # Joint amplitudes over every comb sample: columns delay (x) port offset (x) array.
        col = (np.exp(-2j * np.pi * (fm[:, None, None] + off[None, :, None]) * tau_c)
               * self._steer(uv_c).T[None])  # [M, P, L]
        data = np.moveaxis(h, 2, 1).reshape(m * p, nr)
        c, *_ = np.linalg.lstsq(col.reshape(m * p, -1), data, rcond=None)  # [L, Nr]
        power = np.mean(np.abs(c) ** 2, axis=1)
        order = np.argsort(-power, kind="stable")
        return DelayDirectionProfile(SPEED_OF_LIGHT * tau_c[order], self._world(uv_c[order]),
                                     power[order])
