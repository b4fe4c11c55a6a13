r"""Joint delay-direction estimation at a multi-antenna access point from comb pilots.

The PHY's comb pilots (:class:`~engine.phy.estimation.PilotPattern`, ``"comb"``)
give every transmit antenna (port ``p``) its own comb: port ``p`` sits on the
allocated subcarriers ``p, p + S, p + 2S, ...`` (stride ``S >= P``). The LS
estimates at the combs, ``csi[m, r, p]`` (comb index ``m``, receive antenna
``r``, port ``p``), follow

    ``csi[m, r, p] = sum_l c_{l,r} a_p(k_l) exp(-j 2 pi (m S delta_f + o_p) tau_l)``

with ``o_p`` the port's comb offset [Hz] (``p delta_f`` for the PHY's combs) and
``a_p(k) = exp(+j 2 pi pos_p . k)`` the AP array's steering vector
(:class:`~engine.phy.arrays.PlanarArray`; ``k`` is the departure direction,
world frame, pointing away from the AP). :class:`DelayDirectionEstimator`
returns, per component, the path length ``c tau`` [m], the departure direction
``k`` [3] (unit vector, world axes) and the power ``mean_r |c_{l,r}|^2``:

1. delays: :class:`~engine.phy.estimation.MdpEstimator` (TLS-ESPRIT,
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

from engine.phy._checks import complex_array, positive_float, positive_int, real_array
from engine.phy.arrays import PlanarArray, rotation_matrix
from engine.phy.estimation import MdpEstimator
from engine.phy.units import SPEED_OF_LIGHT

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
        self.rot = rotation_matrix(orientation)
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

    def _direction(self, x: np.ndarray) -> np.ndarray:
        """Direction cosines ``(u, v)`` maximising ``sum_r |a(u, v)^H x_r|^2``
        of a spatial snapshot ``x [P, Nr]``."""
        a = self.array
        n = self.fft_size
        g = np.zeros((n, n, x.shape[1]), complex)
        # element i = c * rows + r sits at y = dh c + y0, z = -dv r + z0
        g[:self._cols, :self._rows] = x.reshape(self._cols, self._rows, -1)
        # sum_c sum_r x exp(-j 2 pi (dh c u - dv r v)) -> DFT over c, inverse DFT over r
        spec = np.fft.ifft(np.fft.fft(g, axis=0), axis=1) * n
        pw = np.sum(np.abs(spec) ** 2, axis=2)
        ic, ir = np.unravel_index(np.argmax(pw), pw.shape)
        fc, fr = np.fft.fftfreq(n)[[ic, ir]]
        u0 = fc / a.horizontal_spacing if self._cols > 1 else 0.0
        v0 = fr / a.vertical_spacing if self._rows > 1 else 0.0
        uv = np.array([u0, v0])
        free = [i for i, m in enumerate((self._cols, self._rows)) if m > 1]

        coords = np.stack([self._y, self._z])  # [2, P] wavelengths
        for _ in range(8):  # Newton on the beam power f = sum_r |a(u, v)^H x_r|^2
            w = np.conj(self._steer(uv[None])[0])[:, None] * x  # [P, Nr]: conj(a_p) x_pr
            b = w.sum(axis=0)  # [Nr]
            b1 = -2j * np.pi * (coords @ w)  # [2, Nr]: d b / d(u, v)
            b2 = -4 * np.pi ** 2 * np.einsum("ip,kp,pr->ikr", coords, coords, w)  # [2, 2, Nr]
            grad = 2 * np.real(np.conj(b)[None] * b1).sum(axis=1)
            hess = 2 * np.real(np.einsum("kr,ir->ik", np.conj(b1), b1)
                               + (np.conj(b)[None, None] * b2).sum(axis=2))
            idx = np.ix_(free, free)
            try:
                step = np.zeros(2)
                step[free] = -np.linalg.solve(hess[idx], grad[free])
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(step)) or np.max(np.abs(step)) > 0.05:
                break  # not in the concave basin of the peak: keep what we have
            uv = uv + step
            if np.max(np.abs(step)) < 1e-7:
                break
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
        comps_tau, comps_uv = [], []
        for t, x in zip(tau, amp):
            xs = (x * np.exp(2j * np.pi * off * t)).T  # [P, Nr], comb offset removed
            uv = self._direction(xs)
            comps_tau.append(t)
            comps_uv.append(uv)
            if self.split_fraction is None:
                continue
            s = self._steer(uv[None])[0]
            res = xs - np.outer(s, np.conj(s) @ xs) / p
            if np.sum(np.abs(res) ** 2) > self.split_fraction * np.sum(np.abs(xs) ** 2):
                comps_tau.append(t)
                comps_uv.append(self._direction(res))
        tau_c = np.asarray(comps_tau)
        uv_c = np.asarray(comps_uv)
        # Joint amplitudes over every comb sample: columns delay (x) port offset (x) array.
        col = (np.exp(-2j * np.pi * (fm[:, None, None] + off[None, :, None]) * tau_c)
               * self._steer(uv_c).T[None])  # [M, P, L]
        data = np.moveaxis(h, 2, 1).reshape(m * p, nr)
        c, *_ = np.linalg.lstsq(col.reshape(m * p, -1), data, rcond=None)  # [L, Nr]
        power = np.mean(np.abs(c) ** 2, axis=1)
        order = np.argsort(-power, kind="stable")
        return DelayDirectionProfile(SPEED_OF_LIGHT * tau_c[order], self._world(uv_c[order]),
                                     power[order])
