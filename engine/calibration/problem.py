"""The calibration problem: what is fitted, to what, and how a fit is scored.

The twin's modelling error comes from materials guessed from inspection and
objects placed by hand. A calibration fits :class:`Parameter` s

* the relative permittivity and/or the conductivity (S/m) of a radio material
  (every Sionna radio material of the scene whose ITU type or name matches),
* the x/y position offset (m) and yaw offset (rad) of named objects,

to :class:`Measurements`, channels measured at known transmitter/receiver
positions, by minimising :func:`mismatch_db2`: the mean squared difference of the
per-subcarrier channel *power* in dB. Magnitudes are blind to a common phase
offset per snapshot (a real receiver's carrier phase) and to a timing offset (a
delay is a linear phase across subcarriers), which is why they are compared
instead of the complex channel. What a fit did is a :class:`CalibrationResult`.

Model assumptions (what a calibration cannot see): planar arrays of
isotropic, vertically polarised elements (the twin's channel model,
:mod:`isac_twin.phy.channel`); specular reflection and refraction
only (no diffuse scattering, no diffraction); the measurement positions are
taken as exact. A parameter whose gradient is zero at the start (no traced
path touches the material or object) is reported as unobserved (:func:`unobserved`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import CalibrationError

#: Parameter kinds: material ones name a radio material, pose ones an object.
MATERIAL_KINDS = ("permittivity", "conductivity")
POSE_KINDS = ("x", "y", "yaw")

#: Default physical bounds per kind (relative permittivity; S/m; m; rad).
#: Offsets are relative to the pose the scene was loaded with.
DEFAULT_BOUNDS = {"permittivity": (1.0, 100.0), "conductivity": (0.0, 1.0e7),
                  "x": (-0.25, 0.25), "y": (-0.25, 0.25), "yaw": (-math.radians(15),
                                                               math.radians(15))}

#: Power floor added before taking dB, W (relative to 1 W transmit power): -200 dB.
POWER_FLOOR = 1e-20


@dataclass(frozen=True)
class Parameter:
    """One parameter to fit.

    Attributes:
        kind: ``"permittivity"``, ``"conductivity"`` (of radio material ``target``),
            ``"x"``, ``"y"`` (offset, m) or ``"yaw"`` (offset, rad) of object ``target``.
        target: ITU type or Sionna material name (material kinds), object name (pose kinds).
        bounds: ``(lower, upper)`` in physical units; default :data:`DEFAULT_BOUNDS`.
        scale: the parameter's typical change, in its units (the optimiser works on
            ``value / scale``); default: 10 % of the start value for materials
            (0.01 S/m at least), 1 cm for x/y, 1 deg for yaw.
    """

    kind: str
    target: str
    bounds: tuple[float, float] | None = None
    scale: float | None = None

    def __post_init__(self):
        if self.kind not in MATERIAL_KINDS + POSE_KINDS:
            raise CalibrationError(f"parameter kind {self.kind!r}: expected one of "
                                   f"{', '.join(MATERIAL_KINDS + POSE_KINDS)}")
        lo, hi = self.bounds if self.bounds is not None else DEFAULT_BOUNDS[self.kind]
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise CalibrationError(f"parameter {self.name}: bounds must be finite with "
                                   f"lower < upper, got {self.bounds!r}")
        if self.kind == "permittivity" and lo < 1.0:
            raise CalibrationError(f"parameter {self.name}: relative permittivity is >= 1, "
                                   f"lower bound {lo} given")
        if self.kind == "conductivity" and lo < 0.0:
            raise CalibrationError(f"parameter {self.name}: conductivity is >= 0 S/m, "
                                   f"lower bound {lo} given")

    @property
    def name(self) -> str:
        return f"{self.target}.{self.kind}"

    @property
    def limits(self) -> tuple[float, float]:
        return tuple(self.bounds if self.bounds is not None else DEFAULT_BOUNDS[self.kind])

    def typical_change(self, start: float) -> float:
        """The optimiser's unit of this parameter (it works on ``value / scale``), in the
        parameter's units: :attr:`scale`, else 10 % of ``start`` for materials (0.01 S/m
        at least), 1 cm for x/y, 1 deg for yaw.

        Raises:
            CalibrationError: a ``scale`` given that is not > 0.
        """
        if self.scale is not None:
            if not self.scale > 0:
                raise CalibrationError(f"parameter {self.name}: scale must be > 0, "
                                       f"got {self.scale}")
            return float(self.scale)
        if self.kind == "permittivity":
            return 0.1 * start
        if self.kind == "conductivity":
            return max(0.1 * start, 0.01)
        return 0.01 if self.kind in ("x", "y") else math.radians(1.0)


@dataclass
class Measurements:
    """Channels measured from one transmitter at N receiver poses.

    Attributes:
        tx_position: ``[3]`` transmitter array centre, m.
        rx_positions: ``[N, 3]`` receiver array centres, m.
        subcarrier_offsets_hz: ``[K]`` subcarrier frequencies relative to the carrier, Hz.
        csi: ``[N, K, Nr, Nt]`` complex channel per antenna pair (``[N, K]`` for one
            pair), transmit power normalised to 1 W; only its magnitude is used.
        tx_array, rx_array: ``(rows, cols, vertical_spacing, horizontal_spacing)``
            (spacings in wavelengths) of isotropic, vertically polarised elements;
            ``rows * cols`` must be ``Nt`` / ``Nr``.
        tx_orientation: ``[3]`` Sionna ``(yaw, pitch, roll)`` of the transmit array, rad.
        rx_orientations: ``[N, 3]`` the same per receiver pose, rad.
        noise_power: ``[N]`` noise variance of each snapshot's CSI per complex sample,
            in the units of ``|csi|^2`` (e.g.
            :func:`isac_twin.phy.estimation.noise_power_from_delay_tail`), or None (an
            exact channel). The model's power gets it added, ``|h|^2 + noise``, the
            expected power of a noisy estimate: without it, a fade the noise fills
            weighs as a model error of tens of dB.
    """

    tx_position: np.ndarray
    rx_positions: np.ndarray
    subcarrier_offsets_hz: np.ndarray
    csi: np.ndarray
    tx_array: tuple = (1, 1, 0.5, 0.5)
    rx_array: tuple = (1, 1, 0.5, 0.5)
    tx_orientation: np.ndarray | None = None
    rx_orientations: np.ndarray | None = None
    noise_power: np.ndarray | None = None

    def __post_init__(self):
        self.tx_position = np.asarray(self.tx_position, float).reshape(-1)
        self.rx_positions = np.atleast_2d(np.asarray(self.rx_positions, float))
        self.subcarrier_offsets_hz = np.asarray(self.subcarrier_offsets_hz, float).reshape(-1)
        self.csi = np.asarray(self.csi, complex)
        n, k = len(self.rx_positions), len(self.subcarrier_offsets_hz)
        if self.csi.ndim == 2:
            self.csi = self.csi[:, :, None, None]
        self.tx_array, self.rx_array = tuple(self.tx_array), tuple(self.rx_array)
        nt = int(self.tx_array[0]) * int(self.tx_array[1])
        nr = int(self.rx_array[0]) * int(self.rx_array[1])
        self.tx_orientation = (np.zeros(3) if self.tx_orientation is None else
                               np.asarray(self.tx_orientation, float).reshape(-1))
        self.rx_orientations = (np.zeros((n, 3)) if self.rx_orientations is None else
                                np.atleast_2d(np.asarray(self.rx_orientations, float)))
        if self.tx_position.shape != (3,):
            raise CalibrationError(f"measurements: tx_position must be [3] m, "
                                   f"got shape {self.tx_position.shape}")
        if self.rx_positions.shape[1:] != (3,):
            raise CalibrationError(f"measurements: rx_positions must be [N, 3] m, "
                                   f"got shape {self.rx_positions.shape}")
        if self.csi.shape != (n, k, nr, nt):
            raise CalibrationError(f"measurements: csi must be [N={n}, K={k}, Nr={nr}, Nt={nt}] "
                                   f"(positions x subcarriers x rx x tx antennas), got shape "
                                   f"{self.csi.shape}")
        if self.tx_orientation.shape != (3,) or self.rx_orientations.shape != (n, 3):
            raise CalibrationError(f"measurements: orientations must be [3] (tx) and "
                                   f"[N={n}, 3] (rx) rad, got {self.tx_orientation.shape} and "
                                   f"{self.rx_orientations.shape}")
        if self.noise_power is not None:
            self.noise_power = np.asarray(self.noise_power, float).reshape(-1)
            if self.noise_power.shape != (n,) or not (
                    np.isfinite(self.noise_power).all() and (self.noise_power >= 0).all()):
                raise CalibrationError(f"measurements: noise_power must be [N={n}] finite "
                                       f"values >= 0 (|csi|^2 units), got "
                                       f"{self.noise_power.tolist()[:4]} of shape "
                                       f"{self.noise_power.shape}")
        for label, a in (("tx_position", self.tx_position), ("rx_positions", self.rx_positions),
                         ("subcarrier_offsets_hz", self.subcarrier_offsets_hz),
                         ("csi", self.csi), ("rx_orientations", self.rx_orientations)):
            if not np.isfinite(a).all():
                raise CalibrationError(f"measurements: {label} has non-finite values")

    def noise_snr_db(self) -> np.ndarray | None:
        """``[N]`` each snapshot's mean channel power over its :attr:`noise_power`, dB
        (None without one)."""
        if self.noise_power is None:
            return None
        power = np.mean(np.abs(self.csi) ** 2, axis=(1, 2, 3))
        return 10.0 * np.log10(power / np.maximum(self.noise_power, 1e-300))


def check_parameters(params: list[Parameter]) -> list[Parameter]:
    """``params`` as a list, at least one and none twice.

    Raises:
        CalibrationError: no parameters, or one given twice.
    """
    if not params:
        raise CalibrationError("calibrate: no parameters to fit")
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        raise CalibrationError(f"calibrate: a parameter is given twice: {names}")
    return list(params)


def as_links(measurements: Measurements | list[Measurements]) -> list[Measurements]:
    """One link's :class:`Measurements`, or a list of them (one per link, on the same
    subcarriers), as a list.

    Raises:
        CalibrationError: no measurements, something else than :class:`Measurements`,
            links measured on other subcarriers.
    """
    links = ([measurements] if isinstance(measurements, Measurements)
             else list(measurements))
    if not links or not all(isinstance(m, Measurements) for m in links):
        raise CalibrationError("calibrate: measurements must be a Measurements or a "
                               "non-empty list of them (one per link)")
    for j, m in enumerate(links[1:], 1):
        if not np.array_equal(m.subcarrier_offsets_hz, links[0].subcarrier_offsets_hz):
            raise CalibrationError(f"calibrate: link {j}'s subcarriers differ from link "
                                   "0's; every link must be measured on the same ones")
    return links


#: A parameter whose scaled start gradient is below this fraction of the largest one
#: is reported as not seen by the measurements.
UNOBSERVED_RATIO = 1e-5


def unobserved(scaled_gradient, names) -> list[str]:
    """Names whose ``|d mismatch / d (value / scale)|`` at the start is at most
    :data:`UNOBSERVED_RATIO` of the largest (all of them when every one is 0): no traced
    path changes with them there (e.g. an object shifted along its own reflecting face)."""
    g = np.abs(np.asarray(scaled_gradient, float))
    top = g.max() if len(g) else 0.0
    return [n for n, v in zip(names, g) if top == 0.0 or v <= UNOBSERVED_RATIO * top]


def power_db(h: np.ndarray) -> np.ndarray:
    """Channel power in dB, ``10 log10(|h|^2 + POWER_FLOOR)``, same shape as ``h``."""
    return 10.0 * np.log10(np.abs(h) ** 2 + POWER_FLOOR)


def mismatch_db2(model: np.ndarray, measured: np.ndarray) -> float:
    """Mean squared per-subcarrier power difference, dB^2 (NumPy reference of the loss)."""
    return float(np.mean((power_db(model) - power_db(measured)) ** 2))


def residual_db(models: list[np.ndarray], links: list[Measurements]) -> np.ndarray:
    """RMS power difference per snapshot, dB, ``[sum N]``: each link's model power
    (``[N, K, Nr, Nt]`` dB) against its measurements, the links' snapshots one after
    the other."""
    return np.concatenate([np.sqrt(np.mean((mod - power_db(m.csi)) ** 2, axis=(1, 2, 3)))
                           for mod, m in zip(models, links)])


@dataclass
class CalibrationResult:
    """What a fit did.

    Attributes:
        names: parameter names (``target.kind``), ``[P]``.
        initial, final: parameter values before/after, physical units, ``[P]``.
        gradient_initial: d mismatch / d parameter at the start, dB^2 per unit, ``[P]``
            (the sensitivity; 0 means the measurements do not see the parameter).
        unobserved: names the measurements do not see at the start (:func:`unobserved`).
        mismatch_initial, mismatch_final: :func:`mismatch_db2`, dB^2.
        residual_db: ``[N]`` RMS power difference per measurement after the fit, dB.
        residual_db_initial: ``[N]`` the same at the scene's values (before), dB.
        converged, message: the optimiser's verdict and reason.
        evaluations: mismatch+gradient evaluations (traces).
        seconds_per_step: mean wall time of one gradient evaluation (trace, CFR, backward), s.
    """

    names: list[str]
    initial: np.ndarray
    final: np.ndarray
    gradient_initial: np.ndarray
    unobserved: list[str]
    mismatch_initial: float
    mismatch_final: float
    residual_db: np.ndarray
    converged: bool
    message: str
    evaluations: int
    seconds_per_step: float
    history: list[float] = field(default_factory=list)
    residual_db_initial: np.ndarray | None = None

    def to_json(self) -> dict:
        """A JSON-serialisable report."""
        return {
            "parameters": [{"name": n, "initial": float(a), "final": float(b),
                            "gradient_initial": float(g)}
                           for n, a, b, g in zip(self.names, self.initial, self.final,
                                                 self.gradient_initial)],
            "unobserved": list(self.unobserved),
            "mismatch_db2": {"initial": self.mismatch_initial, "final": self.mismatch_final},
            "residual_db_per_measurement": [float(r) for r in self.residual_db],
            "residual_db_per_measurement_initial": (
                None if self.residual_db_initial is None else
                [float(r) for r in self.residual_db_initial]),
            "converged": bool(self.converged), "message": self.message,
            "evaluations": self.evaluations, "seconds_per_step": self.seconds_per_step,
            "history_db2": [float(h) for h in self.history],
        }
