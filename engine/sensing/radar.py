r"""OFDM radar processing of received sensing symbols.

Signal model on the sensing resource elements (REs) ``(k, n)`` of one
sensing link (paper eq. 2 with the echo channel of eq. 4)::

    y[k, n, r] = H[k, n, r] x[k, n] + z[k, n, r],
    H[k, n, r] = sum_l b_l a_r(theta_l) exp(j 2 pi (nu_l t_k - f_n tau_l))

Processing chain (:class:`OFDMRadar`):

1. element-wise division by the known symbols: ``H_hat = y / x``
   (zero-forcing "reciprocal filter"; removes the data dependence);
2. optional background subtraction (done by the caller, see
   :class:`~isac_twin.sensing.clutter.BackgroundSubtractor`);
3. windowed 2-D FFT: IFFT over subcarriers -> delay (path length
   ``d = c tau``), FFT over symbols -> Doppler ``nu`` (signed, fftshifted);
   power summed non-coherently over the receive antennas -> range-Doppler
   map ``[Nd, Nrg]``;
4. 2-D cell-averaging CFAR (circular in both axes, as the FFTs are) and
   local-maximum peak picking;
5. super-resolution refinement of every peak: the single-target
   maximum-likelihood (non-linear least-squares) estimate
   ``argmax_{tau, nu} sum_r |e_nu^H H_r e_tau|^2`` searched within +-1 bin
   (bounded scalar searches on the separable kernel, alternated twice),
   which removes the bin quantisation (1.875 m monostatic range bins at
   80 MHz) and approaches the Cramer-Rao bound for an isolated target;
6. angle of arrival over the receive array from the refined
   spatial snapshot ``s_r = e_nu^H H_r e_tau`` ``[Nr]``: beamscan over the
   front hemisphere of the array, refined by a local Nelder-Mead search.

Conventions: subcarrier offsets ``f_n`` and symbol times ``t_k`` follow
:class:`isac_twin.phy.ofdm.ResourceGrid`; sensing REs must be a uniform comb
on both axes (``ResourceSet`` with equally spaced indices). Path length
``d`` is the bistatic range sum ``|T - tx| + |T - rx|`` (monostatic: twice
the range); ``range_rate = dd/dt = -lambda nu``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.optimize

from ..errors import SensingError
from ..phy.arrays import PlanarArray, r_hat, sionna_rotation
from ..phy.ofdm import ResourceSet
from ..phy.units import SPEED_OF_LIGHT

log = logging.getLogger(__name__)

__all__ = ["OFDMRadar", "RangeDopplerMap", "Detection", "ca_cfar", "os_cfar", "SensingError"]


@dataclass
class Detection:
    """One radar detection of a sensing link.

    Attributes:
        link: sensing link name ``"tx->rx"``.
        path_length_m: refined bistatic range sum ``d = c tau`` [m]
            (monostatic: 2 x range).
        range_rate_mps: refined ``dd/dt = -lambda nu`` [m/s]
            (monostatic radial velocity = half of it; > 0 receding).
        doppler_hz: refined Doppler shift ``nu`` [Hz].
        azimuth_rad, zenith_rad: refined arrival direction at the receiver
            (world frame, Sionna convention: from the receiver towards the
            target), NaN when angles are not estimated.
        snr_db: peak power over the CFAR noise estimate [dB].
        range_bin, doppler_bin: integer cell of the range-Doppler map
            (Doppler bin signed, 0 = zero Doppler).
        position: ``[3]`` world position [m] when geolocated, else None.
    """

    link: str
    path_length_m: float
    range_rate_mps: float
    doppler_hz: float
    azimuth_rad: float
    zenith_rad: float
    snr_db: float
    range_bin: int
    doppler_bin: int
    position: np.ndarray | None = None


@dataclass
class RangeDopplerMap:
    """Range-Doppler power map of one frame.

    Attributes:
        power: ``[Nd, Nrg]`` non-coherent power summed over receive antennas
            (Doppler axis fftshifted: row ``Nd // 2`` is zero Doppler).
        path_length_m: ``[Nrg]`` path length of each range cell [m].
        doppler_hz: ``[Nd]`` Doppler of each row [Hz].
        cube: ``[Nr, Nd, Nrg]`` complex range-Doppler data per antenna.
    """

    power: np.ndarray
    path_length_m: np.ndarray
    doppler_hz: np.ndarray
    cube: np.ndarray = field(repr=False)


def _uniform_step(name: str, idx: np.ndarray, axis: str) -> int:
    if idx.size < 2:
        return 1
    d = np.diff(idx)
    if not np.all(d == d[0]):
        raise SensingError(f"sensing link {name!r}: sensing {axis} indices must be "
                           "equally spaced for FFT processing, got spacings "
                           f"{np.unique(d)[:5].tolist()}")
    return int(d[0])


def ca_cfar(power: np.ndarray, guard=(1, 2), train=(2, 8), pfa: float = 1e-6):
    """2-D cell-averaging CFAR on a power map (circular boundaries).

    Args:
        power: ``[Nd, Nrg]`` non-negative power map.
        guard: guard cells ``(doppler, range)`` on each side of the cell under test.
        train: training cells ``(doppler, range)`` beyond the guard cells.
        pfa: design false-alarm probability per cell (exponential noise,
            ``alpha = M (pfa^(-1/M) - 1)`` for ``M`` training cells).

    Returns:
        ``(hits [Nd, Nrg] bool, noise [Nd, Nrg])`` -- the threshold
        crossings and the noise-level estimate per cell.
    """
    p = np.asarray(power, dtype=np.float64)
    gd, gr = (min(int(g), (s - 1) // 2) for g, s in zip(guard, p.shape))
    td, tr = (int(t) for t in train)
    od = min(gd + td, (p.shape[0] - 1) // 2)
    orr = min(gr + tr, (p.shape[1] - 1) // 2)
    outer = (2 * od + 1, 2 * orr + 1)
    inner = (2 * gd + 1, 2 * gr + 1)
    s_out = scipy.ndimage.uniform_filter(p, outer, mode="wrap") * np.prod(outer)
    s_in = scipy.ndimage.uniform_filter(p, inner, mode="wrap") * np.prod(inner)
    m = max(int(np.prod(outer) - np.prod(inner)), 1)
    noise = np.maximum(s_out - s_in, 0.0) / m
    alpha = m * (pfa ** (-1.0 / m) - 1.0)
    return p > alpha * noise, noise


def os_cfar(power: np.ndarray, guard=(1, 2), train=(2, 8), pfa: float = 1e-6,
            rank: float = 0.75):
    """2-D ordered-statistics CFAR (circular): the noise level is the
    ``rank`` quantile of the training ring, so strong neighbours (another
    target in the training cells) do not mask a target as they do in CA-CFAR.

    The scale factor solves ``pfa = prod_{i<k} (M - i) / (M - i + alpha)``
    (exponential noise, ``k = rank * M``). Returns ``(hits, noise)`` like
    :func:`ca_cfar` (``noise``: the k-th ordered training value).
    """
    p = np.asarray(power, dtype=np.float64)
    gd, gr = (min(int(g), (s - 1) // 2) for g, s in zip(guard, p.shape))
    od = min(gd + int(train[0]), (p.shape[0] - 1) // 2)
    orr = min(gr + int(train[1]), (p.shape[1] - 1) // 2)
    fp = np.ones((2 * od + 1, 2 * orr + 1), dtype=bool)
    fp[od - gd:od + gd + 1, orr - gr:orr + gr + 1] = False
    m = int(fp.sum())
    k = min(max(int(round(rank * m)), 1), m)
    kth = scipy.ndimage.rank_filter(p, k - 1, footprint=fp, mode="wrap")
    i = np.arange(k)
    f = lambda a: np.sum(np.log(m - i) - np.log(m - i + a)) - np.log(pfa)  # noqa: E731
    alpha = scipy.optimize.brentq(f, 1e-9, 1e9)
    return p > alpha * kth, kth


class OFDMRadar:
    """OFDM radar processor for one sensing link.

    Args:
        resource_set: the sensing REs (uniform comb in subcarriers and symbols)
            on the step's grid; its ``name`` names the link in errors.
        carrier_frequency_hz: f_c [Hz] (for range rate and array phases).
        rx_array: receive array (``None`` or one element: no angles).
        rx_orientation: receive array orientation ``[yaw, pitch, roll]`` [rad]
            (``isac_twin.phy`` / Sionna order).
        estimate_angles: estimate azimuth/zenith (needs >= 2 receive elements).
        range_oversampling, doppler_oversampling: zero-padding factors of the FFTs.
        window: ``"hann"`` or ``"rect"`` taper for the FFTs.
        cfar: ``"ca"`` (:func:`ca_cfar`) or ``"os"`` (:func:`os_cfar`, robust
            to a second target in the training cells, slower).
        guard, train, pfa: CFAR parameters (see :func:`ca_cfar`); the
            default guard covers the window's main lobe (Hann: 2 bins, times
            the oversampling) so a target does not mask itself.
        max_detections: keep at most this many strongest peaks.
        max_path_length_m: ignore cells beyond this path length [m] (None: all).
        min_path_length_m: ignore cells below it [m] (e.g. the direct leakage).
        angle_grid_deg: beamscan grid step [deg].
        range_method: ``"nls"`` (single-target ML refinement, best for an
            isolated point target) or ``"first_arrival"``: after NLS and
            angle, TLS-ESPRIT + least squares
            (:class:`isac_twin.phy.estimation.MdpEstimator`) on the
            beamformed, Doppler-compensated subcarrier response resolves the
            echo's multipath (e.g. floor bounces, unresolvable at 80 MHz)
            and the earliest component within ``first_arrival_db`` of the
            strongest one near the peak is taken (the direct echo is the
            shortest path that touches the target).
        esprit_paths: model-order cap of the ESPRIT step.
        first_arrival_db: power window of the first-arrival pick [dB].
    """

    def __init__(self, resource_set: ResourceSet, carrier_frequency_hz: float, *,
                 rx_array: PlanarArray | None = None, rx_orientation=(0.0, 0.0, 0.0),
                 estimate_angles: bool = True, range_oversampling: int = 4,
                 doppler_oversampling: int = 2, window: str = "hann",
                 cfar: str = "ca", guard=None, train=(3, 8), pfa: float = 1e-6,
                 max_detections: int = 8, max_path_length_m: float | None = None,
                 min_path_length_m: float = 0.0, angle_grid_deg: float = 2.0,
                 range_method: str = "nls", esprit_paths: int = 4,
                 first_arrival_db: float = 12.0) -> None:
        if range_method not in ("nls", "first_arrival"):
            raise SensingError(f"sensing link {resource_set.name!r}: range_method must be "
                               f"'nls' or 'first_arrival', got {range_method!r}")
        self.range_method = range_method
        self.esprit_paths = int(esprit_paths)
        self.first_arrival_db = float(first_arrival_db)
        if not isinstance(resource_set, ResourceSet):
            raise SensingError("resource_set must be an isac_twin.phy.ResourceSet")
        self.name = resource_set.name
        self.rs = resource_set
        self.fc = float(carrier_frequency_hz)
        if not self.fc > 0:
            raise SensingError(f"sensing link {self.name!r}: carrier frequency must be > 0")
        self.wavelength = SPEED_OF_LIGHT / self.fc
        grid = resource_set.grid
        self.sc = resource_set.subcarrier_indices
        self.sy = resource_set.symbol_indices
        self.sc_step = _uniform_step(self.name, self.sc, "subcarrier")
        self.sy_step = _uniform_step(self.name, self.sy, "symbol")
        self.f = grid.subcarrier_frequencies[self.sc]  # [Ns] Hz
        self.t = grid.symbol_times[self.sy]  # [Ks] s
        self.df = grid.subcarrier_spacing_hz * self.sc_step
        self.dt = grid.symbol_duration_s * self.sy_step
        if window not in ("hann", "rect"):
            raise SensingError(f"sensing link {self.name!r}: window must be 'hann' or 'rect'")
        self.window = window
        self.ros = int(range_oversampling)
        self.dos = int(doppler_oversampling)
        lobe = 2 if window == "hann" else 1
        self.guard = guard if guard is not None else (lobe * self.dos, lobe * self.ros)
        self.train, self.pfa = train, float(pfa)
        if cfar not in ("ca", "os"):
            raise SensingError(f"sensing link {self.name!r}: cfar must be 'ca' or 'os', "
                               f"got {cfar!r}")
        self.cfar = cfar
        self.max_detections = int(max_detections)
        self.max_d = max_path_length_m
        self.min_d = float(min_path_length_m)
        self.rx_array = rx_array
        self.rx_orientation = tuple(float(v) for v in rx_orientation)
        nr = rx_array.num_ant if rx_array is not None else 1
        if estimate_angles and nr < 2:
            raise SensingError(
                f"sensing link {self.name!r}: angles requested but the receiver has "
                f"{nr} antenna element(s); give the link a receive array with >= 2 "
                "elements (e.g. swap tx/rx so the multi-antenna AP receives) or set "
                "estimate_angles=False")
        self.estimate_angles = bool(estimate_angles)
        self.num_rx = nr
        self._scan = None
        if self.estimate_angles:
            self._scan = self._beamscan_grid(angle_grid_deg)

    # ------------------------------------------------------------------ axes

    @property
    def range_resolution_m(self) -> float:
        """Path-length resolution ``c / (Ns df)`` [m] (monostatic range: half)."""
        return SPEED_OF_LIGHT / (self.sc.size * self.df)

    @property
    def max_unambiguous_path_m(self) -> float:
        """``c / df`` [m]."""
        return SPEED_OF_LIGHT / self.df

    @property
    def doppler_resolution_hz(self) -> float:
        """``1 / (Ks dt)`` [Hz]."""
        return 1.0 / (self.sy.size * self.dt)

    def _win(self, n: int) -> np.ndarray:
        return np.hanning(n + 2)[1:-1] if (self.window == "hann" and n > 2) else np.ones(n)

    # ------------------------------------------------------------------ steps

    def channel_estimate(self, y, x) -> np.ndarray:
        """Divide the received sensing REs by the known symbols.

        Args:
            y: ``[Ks, Ns, Nr]`` received samples on the sensing REs, or the
                full grid ``[K, N, Nr]`` (the sensing REs are picked out).
            x: ``[Ks, Ns]`` or ``[K, N]`` known transmitted symbols (non-zero
                on the sensing REs).

        Returns:
            ``H_hat [Ks, Ns, Nr]`` complex128.
        """
        y = np.asarray(y)
        x = np.asarray(x)
        ks, ns = self.sy.size, self.sc.size
        k, n = self.rs.grid.shape
        if y.ndim == 2:
            y = y[..., None]
        if y.ndim != 3:
            raise SensingError(f"sensing link {self.name!r}: y must be [K, N, Nr], "
                               f"got shape {list(y.shape)}")
        if y.shape[:2] == (k, n) and (k, n) != (ks, ns):
            y = y[np.ix_(self.sy, self.sc)]
        if x.shape == (k, n) and (k, n) != (ks, ns):
            x = x[np.ix_(self.sy, self.sc)]
        if y.shape[:2] != (ks, ns) or x.shape != (ks, ns):
            raise SensingError(
                f"sensing link {self.name!r}: y {list(y.shape)} / x {list(x.shape)} do not "
                f"match the sensing REs [{ks}, {ns}] or the grid [{k}, {n}]")
        if y.shape[2] != self.num_rx:
            raise SensingError(f"sensing link {self.name!r}: y has {y.shape[2]} receive "
                               f"antennas, the receive array has {self.num_rx}")
        if np.any(x == 0):
            raise SensingError(f"sensing link {self.name!r}: known symbols x are zero on "
                               "some sensing REs")
        return y / x[..., None]

    def range_doppler(self, h) -> RangeDopplerMap:
        """Windowed 2-D FFT of ``h [Ks, Ns, Nr]`` -> :class:`RangeDopplerMap`."""
        h = np.asarray(h)
        ks, ns, nr = h.shape
        w = self._win(ks)[:, None] * self._win(ns)[None, :]
        nrg = ns * self.ros
        nd = ks * self.dos
        # Antenna-major layout so both FFTs run over contiguous memory.
        hw = np.ascontiguousarray(np.moveaxis(h, 2, 0)) * w  # [Nr, Ks, Ns]
        # Delay: sum_n H e^{+j 2 pi n m / Nrg}  (f_n tau term has a minus sign).
        cube = scipy.fft.ifft(hw, n=nrg, axis=2, norm="forward")
        # Doppler: sum_k H e^{-j 2 pi k q / Nd}.
        cube = np.fft.fftshift(scipy.fft.fft(cube, n=nd, axis=1), axes=1)  # [Nr, Nd, Nrg]
        power = np.sum(cube.real ** 2 + cube.imag ** 2, axis=0)
        d = np.arange(nrg) * (self.max_unambiguous_path_m / nrg)
        nu = (np.arange(nd) - nd // 2) / (nd * self.dt)
        return RangeDopplerMap(power=power, path_length_m=d, doppler_hz=nu, cube=cube)

    def detect_cells(self, rd: RangeDopplerMap):
        """CFAR + local-maximum peaks: ``[(doppler_row, range_col, snr_db), ...]``
        strongest first, at most ``max_detections``."""
        fn = ca_cfar if self.cfar == "ca" else os_cfar
        hits, noise = fn(rd.power, self.guard, self.train, self.pfa)
        peak = rd.power >= scipy.ndimage.maximum_filter(rd.power, size=(3, 3), mode="wrap")
        ok = hits & peak
        if self.max_d is not None:
            ok &= (rd.path_length_m <= self.max_d)[None, :]
        ok &= (rd.path_length_m >= self.min_d)[None, :]
        rows, cols = np.nonzero(ok)
        if rows.size == 0:
            return []
        pw = rd.power[rows, cols]
        order = np.argsort(-pw)[: self.max_detections]
        snr = 10 * np.log10(pw[order] / np.maximum(noise[rows[order], cols[order]], 1e-300))
        return [(int(rows[i]), int(cols[i]), float(s)) for i, s in zip(order, snr)]

    def _refine(self, h: np.ndarray, d0: float, nu0: float):
        """Single-target NLS refinement around ``(d0 [m], nu0 [Hz])``.

        Returns ``(d, nu, snapshot [Nr])``.
        """
        fc = self.f / SPEED_OF_LIGHT  # cycles per metre
        hw = h * self._win(h.shape[1])[None, :, None]
        wk = self._win(h.shape[0])

        def g_of_d(d):  # [Ks, Nr]: H contracted with the delay steering e^{+j2pi f d / c}
            return np.einsum("knr,n->kr", hw, np.exp(2j * np.pi * fc * d))

        def snap(g, nu):
            return np.einsum("kr,k->r", g, wk * np.exp(-2j * np.pi * self.t * nu))

        d, nu = d0, nu0
        dd = self.max_unambiguous_path_m / (self.sc.size * self.ros) * 1.5
        dnu = 1.0 / (self.sy.size * self.dos * self.dt) * 1.5
        g = g_of_d(d)
        for _ in range(2):
            if self.sy.size > 1:
                r = scipy.optimize.minimize_scalar(
                    lambda v: -np.sum(np.abs(snap(g, v)) ** 2), bounds=(nu - dnu, nu + dnu),
                    method="bounded", options={"xatol": 1e-4 * dnu})
                nu = float(r.x)
            ek = wk * np.exp(-2j * np.pi * self.t * nu)
            gk = np.einsum("knr,k->nr", hw, ek)  # [Ns, Nr]
            r = scipy.optimize.minimize_scalar(
                lambda v: -np.sum(np.abs(np.exp(2j * np.pi * fc * v) @ gk) ** 2),
                bounds=(d - dd, d + dd), method="bounded", options={"xatol": 1e-5 * dd})
            d = float(r.x)
            g = g_of_d(d)
        return d, nu, snap(g, nu)

    def _first_arrival(self, h, d, nu, az, ze) -> float:
        """Earliest multipath component near ``d`` (see ``range_method``)."""
        from ..phy.estimation import MdpEstimator

        ek = np.exp(-2j * np.pi * self.t * nu)
        if self.estimate_angles:
            a = self.rx_array.steering_vectors(np.array([ze]), np.array([az]),
                                               self.rx_orientation)[0]
            r = np.einsum("knr,r,k->n", h, np.conj(a), ek)
        else:
            r = np.einsum("knr,k->n", h, ek)
        try:
            m = MdpEstimator(self.df, max_paths=self.esprit_paths, order="mdl")(r, self.f)
        except (ValueError, np.linalg.LinAlgError) as exc:  # pragma: no cover - degenerate
            log.debug("sensing link %s: ESPRIT failed (%s); keeping NLS", self.name, exc)
            return d
        if len(m) == 0:
            return d
        res = self.range_resolution_m
        near = (m.distances_m >= d - res) & (m.distances_m <= d + 0.5 * res)
        strong = m.powers >= m.powers[near].max() * 10 ** (-self.first_arrival_db / 10) \
            if near.any() else near
        ok = near & strong
        return float(m.distances_m[ok].min()) if ok.any() else d

    def _beamscan_grid(self, step_deg: float):
        """Front-hemisphere grid of directions (world frame) and steering vectors."""
        rot = sionna_rotation(self.rx_orientation)
        a = self.rx_array
        step = np.deg2rad(step_deg)
        az = np.arange(-np.pi / 2 + step / 2, np.pi / 2, step)
        el = np.arange(-np.pi / 2 + step / 2, np.pi / 2, step) if a.num_rows > 1 \
            else np.array([0.0])
        if a.num_cols == 1:
            az = np.array([0.0])
        azg, elg = np.meshgrid(az, el, indexing="ij")
        loc = np.stack([np.cos(elg) * np.cos(azg), np.cos(elg) * np.sin(azg), np.sin(elg)], -1)
        world = loc.reshape(-1, 3) @ rot.T
        sv = a.steering_vectors_from_directions(world, self.rx_orientation)  # [G, Nr]
        return world, sv

    def _angle(self, s: np.ndarray):
        """Arrival ``(azimuth, zenith)`` [rad] (world) from a snapshot ``s [Nr]``."""
        world, sv = self._scan
        spec = np.abs(np.conj(sv) @ s) ** 2
        k0 = world[int(np.argmax(spec))]
        rot = sionna_rotation(self.rx_orientation)
        loc0 = rot.T @ k0
        x0 = np.array([np.arctan2(loc0[1], loc0[0]), np.arcsin(np.clip(loc0[2], -1, 1))])

        if self.rx_array.pattern == "iso":
            # the rotated element positions once per search, not per evaluation (the
            # same operations as PlanarArray.steering_vectors_from_directions)
            pos_t = (self.rx_array.normalized_positions @ rot.T).T  # [3, Nr]

            def steer(k):
                return np.exp(1j * (2.0 * np.pi * (k[None] @ pos_t)))[0]
        else:
            def steer(k):
                return self.rx_array.steering_vectors_from_directions(
                    k[None], self.rx_orientation)[0]

        def cost(v):
            az, el = v
            kl = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            return -np.abs(np.vdot(steer(rot @ kl), s)) ** 2

        r = scipy.optimize.minimize(cost, x0, method="Nelder-Mead",
                                    options={"xatol": 1e-4, "fatol": 1e-12 * -cost(x0),
                                             "maxiter": 200})
        az, el = r.x
        if self.rx_array.num_rows == 1:
            el = 0.0  # a horizontal line array cannot see elevation: assume horizontal
        if self.rx_array.num_cols == 1:
            az = 0.0
        kl = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        k = rot @ kl
        return float(np.arctan2(k[1], k[0])), float(np.arccos(np.clip(k[2], -1, 1)))

    def process(self, h, rd: RangeDopplerMap | None = None
                ) -> tuple[list[Detection], RangeDopplerMap]:
        """Range-Doppler map, CFAR and refinement of a channel estimate.

        Args:
            h: ``[Ks, Ns, Nr]`` channel estimate on the sensing REs (after
                any background subtraction).
            rd: a precomputed map of ``h`` (optional).

        Returns:
            ``(detections, range_doppler_map)``.
        """
        h = np.asarray(h, dtype=np.complex128)
        if h.ndim != 3 or h.shape[:2] != (self.sy.size, self.sc.size):
            raise SensingError(f"sensing link {self.name!r}: h must be "
                               f"[{self.sy.size}, {self.sc.size}, Nr], got {list(h.shape)}")
        rd = rd if rd is not None else self.range_doppler(h)
        out = []
        nd = rd.doppler_hz.size
        for row, col, snr in self.detect_cells(rd):
            d, nu, s = self._refine(h, float(rd.path_length_m[col]), float(rd.doppler_hz[row]))
            az = ze = float("nan")
            if self.estimate_angles:
                az, ze = self._angle(s)
            if self.range_method == "first_arrival":
                d = self._first_arrival(h, d, nu, az, ze)
            out.append(Detection(link=self.name, path_length_m=d,
                                 range_rate_mps=-self.wavelength * nu, doppler_hz=nu,
                                 azimuth_rad=az, zenith_rad=ze, snr_db=snr,
                                 range_bin=col, doppler_bin=row - nd // 2))
        return out, rd

    def __call__(self, y, x):
        """``y [Ks, Ns, Nr]`` (or full grid), known ``x`` -> ``(detections, map)``."""
        return self.process(self.channel_estimate(y, x))


def direction(azimuth, zenith) -> np.ndarray:
    """Unit vector ``[3]`` from azimuth/zenith [rad] (Sionna convention)."""
    return r_hat(zenith, azimuth)
