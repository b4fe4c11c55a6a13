"""Calibrate the twin from measured channels: fit materials and object poses (issue 20).

The twin's modelling error comes from materials guessed from inspection and
objects placed by hand. :class:`Calibrator` fits

* the relative permittivity and/or the conductivity (S/m) of a radio material
  (every Sionna radio material of the scene whose ITU type or name matches),
* the x/y position offset (m) and yaw offset (rad) of named objects,

to channels measured at known transmitter/receiver positions, by minimising
:func:`mismatch_db2`: the mean squared difference of the per-subcarrier
channel *power* in dB. Magnitudes are blind to a common phase offset per
snapshot (a real receiver's carrier phase) and to a timing offset (a delay is
a linear phase across subcarriers), which is why they are compared instead of
the complex channel.

Gradients come from Sionna RT through Dr.Jit's automatic differentiation on
the LLVM backend: the material parameters are Dr.Jit variables of Sionna's
``RadioMaterial`` (its ITU frequency callback is switched off so the fitted
value sticks), the object offsets move the mesh vertices through Mitsuba's
scene parameters, and ``PathSolver`` (``loop_mode="evaluated"``, the mode
Sionna documents as differentiable) plus ``Paths.cfr`` propagate both to the
channel. Paths are re-traced at every evaluation with a fixed seed, so the
mismatch is a deterministic function of the parameters. SciPy's L-BFGS-B
keeps every parameter inside its physical bounds and decides convergence
(relative mismatch change or projected gradient below tolerance); the result
says whether it converged and why.

Model assumptions (what a calibration cannot see): planar arrays of
isotropic, vertically polarised elements (the twin's channel model,
:mod:`isac_twin.phy.channel`); specular reflection and refraction
only (no diffuse scattering, no diffraction); the measurement positions are
taken as exact. A parameter whose gradient is zero at the start (no traced
path touches the material or object) is reported as unobserved.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import CalibrationError

log = logging.getLogger(__name__)

#: Parameter kinds: material ones name a radio material, pose ones an object.
MATERIAL_KINDS = ("permittivity", "conductivity")
POSE_KINDS = ("x", "y", "yaw")

#: Default physical bounds per kind (relative permittivity; S/m; m; rad).
#: Offsets are relative to the pose the scene was loaded with.
DEFAULT_BOUNDS = {"permittivity": (1.0, 100.0), "conductivity": (0.0, 1.0e7),
                  "x": (-0.25, 0.25), "y": (-0.25, 0.25), "yaw": (-math.radians(15),
                                                               math.radians(15))}

#: :meth:`Calibrator.fit` with ``trust``: another round while the last one lowered the
#: mismatch by more than this fraction.
ROUND_GAIN = 0.01

#: Trial steps of one L-BFGS-B line search in a trust-box round of :meth:`Calibrator.fit`
#: (SciPy's default 20 without ``trust``: near an exact minimum, 1e-9 dB^2, the shorter
#: search ended "ABNORMAL" where SciPy's converged). Where a path appears or
#: disappears the mismatch jumps and the line search fails; SciPy then shrank the step
#: 20 times down to moves too small to change a float32 vertex (lab: 20 evaluations
#: at exactly 1.7018 dB^2, 200 of the first fit's 324).
MAX_LINE_SEARCH = 6

#: L-BFGS-B's "ABNORMAL" line-search end counts as converged when this many last
#: evaluations all equal the best mismatch (:func:`_flat_tail`).
FLAT_TAIL = 4


def _flat_tail(history: list[float]) -> bool:
    """The last :data:`FLAT_TAIL` mismatches all equal the lowest one seen."""
    return len(history) >= FLAT_TAIL and all(f == min(history) for f in history[-FLAT_TAIL:])


#: :meth:`Calibrator.polish`: first and last step of each parameter, in its ``scale``
#: (x/y 0.5 -> 0.0625 cm, yaw 0.5 -> 0.0625 deg, a material 5 % -> 0.625 %).
POLISH_STEPS = (0.5, 0.0625)

#: :meth:`Calibrator.polish` with chains: enumerate them again after a sweep that
#: moved something once this many traces were made on the last ones (and at the end).
POLISH_REFRESH_TRACES = 40

#: :meth:`Calibrator.hop`: the scan of an x/y offset covers shifts between these many
#: wavelengths to either side of its value, in steps of 1 / :data:`HOP_PER_WAVELENGTH`
#: wavelength. The magnitude mismatch has a local minimum about every half wavelength
#: of an object's shift normal to a face it reflects on (period lambda / (2 cos theta)
#: >= lambda / 2), so the next basins lie beyond the current one's quarter period; a
#: basin is about +-1 cm wide at 2.4 GHz (lab, Table_2's y: period ~7 cm, 0.40 dB^2 at
#: 0.2 cm from the bottom of its true basin, 0.43-0.68 dB^2 at 0.6-1.7 cm).
HOP_SPAN = (0.3, 0.6)
HOP_PER_WAVELENGTH = 12
#: The lowest other basin of every scan is searched, whatever its scan points say: the
#: points miss a basin's bottom by up to half a step, and with the chain model a
#: basin is narrow (lab, 32 subcarriers: Table_2's y a period off, its true basin
#: scanned 0.43 dB^2 at the nearest point, 2.1 x the current 0.204, and its bottom
#: was 0.085; a limit of 1.25 x left it a period off). This many times the current
#: mismatch is the limit (a basin scanned higher is not searched).
HOP_SLACK = 4.0
#: ... and a searched basin is kept only when it lowers the mismatch by more than this
#: fraction (a shift along a face the lap does not see scans flat to ~1 %: lab, Table_2's
#: x, 0.287-0.293 dB^2 over 16 cm).
HOP_GAIN = 0.01
#: ... and by more than this, dB^2 (0.03 dB RMS): at a noise-free fit's 1e-7 dB^2, 1 %
#: is float noise, and a flat shift moved 4.7 cm for it.
HOP_MIN_GAIN_DB2 = 1e-3
#: ... and, for a coordinate the start gradient did not see (``unseen``), by more than
#: this fraction: along a face the lap does not see, the mismatch scans flat to ~2 %
#: (lab: Table_2's x, 0.287-0.293 dB^2 over 16 cm), so 1 % moved SwitchBox_2's unseen
#: y by 9.9 cm for a 1.1 % gain; where a path appears the gain is larger (Chair_2's x:
#: 5.5 % and 7.4 % in two runs).
HOP_GAIN_UNSEEN = 0.03

#: ``max_num_paths_per_src`` of the candidate generator (Sionna's default).
MAX_CANDIDATES = 1_000_000

#: Sionna's deterministic candidate generator (``PathSolver(deterministic=True)``) keeps,
#: per chain of planes, the ray of the lowest index instead of whichever thread wins a
#: race on its hash table, so it runs on every thread and gives the same candidates on
#: every call (lab, 2 cores: 0.14 s, against 0.33 s for the default generator, which had
#: to run on one thread to be repeatable). Its memory grows with depth x rays x snapshots
#: (one 64-bit hash per lane); above this many lanes the default generator runs instead,
#: on one thread.
DETERMINISTIC_LANES = 1 << 26

#: With ``SolverSettings.chains``: a receiver is given the chains that mirror geometry
#: allows (:class:`~isac_twin.raytrace.source_chains.MirrorFilter`) with this margin, m,
#: around each reflecting plane's triangles: the objects move between enumerations
#: (the calibration's offsets are a few cm), and a chain the filter drops is never
#: traced. Lab: about 1/7 of the (chain, receiver) pairs at 1 mm.
CHAIN_FILTER_MARGIN = 0.1

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


def local_minima(f: np.ndarray) -> np.ndarray:
    """Indices of the local minima of ``f [S]`` (ends included), lowest first."""
    f = np.asarray(f, float)
    idx = [i for i in range(len(f)) if (i == 0 or f[i] <= f[i - 1])
           and (i == len(f) - 1 or f[i] <= f[i + 1])]
    return np.array(sorted(idx, key=lambda i: f[i]), int)


def power_db(h: np.ndarray) -> np.ndarray:
    """Channel power in dB, ``10 log10(|h|^2 + POWER_FLOOR)``, same shape as ``h``."""
    return 10.0 * np.log10(np.abs(h) ** 2 + POWER_FLOOR)


def mismatch_db2(model: np.ndarray, measured: np.ndarray) -> float:
    """Mean squared per-subcarrier power difference, dB^2 (NumPy reference of the loss)."""
    return float(np.mean((power_db(model) - power_db(measured)) ** 2))


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


@dataclass(frozen=True)
class _LinkGroup:
    """One link of a :class:`Calibrator`: its transmitter (``src``: Dr.Jit position,
    orientation, array element offsets) and its snapshots' receivers (``tgt``), ``n``
    snapshots, the antennas at either end, the arrays' patterns, the measured power
    (dB, float64 ``[N * Nr * Nt * K]``), the link's weight in the mismatch (its
    share of all snapshots) and the measurements' noise variance added to the model's
    power (float64 ``[N * Nr * Nt * K]``, or None)."""

    src: tuple
    tgt: tuple
    n: int
    n_tx_ant: int
    n_rx_ant: int
    patterns: tuple
    meas_db: object
    weight: float
    noise: object = None


@dataclass(frozen=True)
class SolverSettings:
    """Path solver settings of the calibration's traces.

    Attributes:
        max_depth: interactions per path.
        samples_per_src: rays shot per transmitter.
        seed: the ray sampler's seed (fixed: the mismatch must be deterministic).
        refraction: trace transmission through objects.
        chains: the model's candidates are the chains of the transmitters (every
            chain of ``samples_per_src`` branching rays, enumerated when the
            calibrator refreshes them, each tried to every receiver by the image
            method), as the twin's chain tracer finds paths
            (:mod:`isac_twin.raytrace.chains`); False: Sionna's candidate generator at
            every trace (its sampled candidates, as ``PathSolver``'s).
    """

    max_depth: int = 2
    samples_per_src: int = 20000
    seed: int = 1
    refraction: bool = True
    chains: bool = False

    @classmethod
    def from_tracer(cls, tracer) -> SolverSettings:
        """The settings of a scene's ``[tracer]`` (:class:`isac_twin.scene.config.TracerConfig`), so
        the model sees the paths the twin's tracer sees.

        Raises:
            CalibrationError: diffuse reflection or diffraction is on (not modelled).
        """
        if tracer.diffuse_reflection or tracer.diffraction or not tracer.los:
            raise CalibrationError("calibrate: the scene's [tracer] has diffuse reflection, "
                                   "diffraction or no line of sight; the calibration models "
                                   "line of sight, specular reflection and refraction only")
        return cls(max_depth=tracer.max_depth, samples_per_src=tracer.samples_per_src,
                   seed=tracer.seed, refraction=tracer.refraction, chains=tracer.uses_chains)


class Calibrator:
    """Fits :class:`Parameter` s of a scene to :class:`Measurements`.

    The calibrator owns ``scene`` (a freshly loaded :class:`~isac_twin.scene.twin_scene.TwinScene`):
    it adds its own transmitter and receivers, replaces the scene's arrays by one
    isotropic element and switches the fitted materials' ITU frequency callback off.
    Object offsets are written straight into Mitsuba's vertex buffers, which the
    ``TwinScene``'s edit bookkeeping (``object_poses``, ``content_hash``) does not
    see: do not trace the twin with this scene afterwards; load the calibrated
    folder (:func:`isac_twin.calibration.run.write_calibrated_scene`) instead.

    Args:
        scene: the twin's scene (``isac_twin.scene.twin_scene.load_scene``).
        measurements: what was measured: one link's :class:`Measurements`, or a list
            of them, one per link (transmitter), on the same subcarriers; each
            snapshot counts the same in the mismatch, whichever its link.
        params: what to fit (at least one).
        solver: :class:`SolverSettings`.

    Raises:
        CalibrationError: unknown material/object, a parameter given twice, no
            measurements, links measured on other subcarriers.
    """

    def __init__(self, scene, measurements: Measurements | list[Measurements],
                 params: list[Parameter],
                 solver: SolverSettings | None = None):
        import drjit as dr
        import mitsuba as mi
        import sionna.rt as rt

        self._dr, self._mi = dr, mi
        if not params:
            raise CalibrationError("calibrate: no parameters to fit")
        names = [p.name for p in params]
        if len(set(names)) != len(names):
            raise CalibrationError(f"calibrate: a parameter is given twice: {names}")
        self.params = list(params)
        #: The measurements, one :class:`Measurements` per link.
        self.links = ([measurements] if isinstance(measurements, Measurements)
                      else list(measurements))
        self._one_link = isinstance(measurements, Measurements)
        if not self.links or not all(isinstance(m, Measurements) for m in self.links):
            raise CalibrationError("calibrate: measurements must be a Measurements or a "
                                   "non-empty list of them (one per link)")
        for j, m in enumerate(self.links[1:], 1):
            if not np.array_equal(m.subcarrier_offsets_hz, self.links[0].subcarrier_offsets_hz):
                raise CalibrationError(f"calibrate: link {j}'s subcarriers differ from link "
                                       "0's; every link must be measured on the same ones")
        self.settings = solver or SolverSettings()
        self.sc = sc = scene.sionna
        self.evaluations = 0
        #: Wall time of each gradient evaluation / of each evaluation without, s.
        self.step_seconds: list[float] = []
        self.forward_seconds: list[float] = []

        # materials: every Sionna radio material whose ITU type or name matches
        self._materials: dict[str, list] = {}
        for p in self.params:
            if p.kind in MATERIAL_KINDS and p.target not in self._materials:
                mats = [m for m in sc.radio_materials.values()
                        if getattr(m, "itu_type", None) == p.target or m.name == p.target]
                if not mats:
                    have = sorted({getattr(m, "itu_type", m.name)
                                   for m in sc.radio_materials.values()})
                    raise CalibrationError(f"calibrate: parameter {p.name}: no radio material "
                                           f"{p.target!r} in the scene (have: {', '.join(have)})")
                for m in mats:
                    m.frequency_update_callback = None  # keep the fitted value
                self._materials[p.target] = mats
        # objects: original vertices and bounding-box centre
        self._objects: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}
        params_mi = sc.mi_scene_params
        for p in self.params:
            if p.kind in POSE_KINDS and p.target not in self._objects:
                obj = sc.objects.get(p.target)
                if obj is None:
                    raise CalibrationError(f"calibrate: parameter {p.name}: no object "
                                           f"{p.target!r} (objects: {', '.join(sc.objects)})")
                key = obj.mi_mesh.id() + ".vertex_positions"
                v = np.array(params_mi[key].numpy(), dtype=np.float64).reshape(-1, 3)
                centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
                # the vertices about the centre as Dr.Jit arrays made once: arrays made
                # afresh from NumPy at every evaluation landed at other alignments, and
                # Dr.Jit compiled the vertex kernel anew for each (2 x 80 ms per
                # evaluation on the lab, of 0.62 s)
                rel = [mi.Float(v[:, 0] - centre[0]), mi.Float(v[:, 1] - centre[1]),
                       mi.Float(v[:, 2])]
                dr.eval(rel)
                self._objects[p.target] = (key, v, centre, rel)

        self.initial = np.array([self._current(p) for p in self.params])
        for p, v in zip(self.params, self.initial):
            lo, hi = p.limits
            if not lo <= v <= hi:
                raise CalibrationError(f"calibrate: parameter {p.name} starts at {v:g}, "
                                       f"outside its bounds [{lo:g}, {hi:g}]")
        self.scales = np.array([self._scale(p, v) for p, v in zip(self.params, self.initial)])

        # devices: one isotropic V element at each array centre
        def array(spec):
            rows, cols, dv, dh = spec
            return rt.PlanarArray(num_rows=int(rows), num_cols=int(cols),
                                  vertical_spacing=float(dv), horizontal_spacing=float(dh),
                                  pattern="iso", polarization="V")

        for name in [n for n in list(sc.transmitters) + list(sc.receivers)]:
            sc.remove(name)
        # one transmitter per link, one receiver per snapshot; each link is traced on its
        # own (a trace of every transmitter to every receiver would trace pairs that were
        # not measured)
        self._groups = []
        n_all = sum(len(m.rx_positions) for m in self.links)
        for j, m in enumerate(self.links):
            tx = rt.Transmitter(f"calib_tx{j}", position=mi.Point3f(*map(float, m.tx_position)),
                                orientation=mi.Point3f(*map(float, m.tx_orientation)))
            rxs = [rt.Receiver(f"calib_rx{j}_{i:04d}", position=mi.Point3f(*map(float, pos)),
                               orientation=mi.Point3f(*map(float, ori)))
                   for i, (pos, ori) in enumerate(zip(m.rx_positions, m.rx_orientations))]
            sc.add(tx)
            for r in rxs:
                sc.add(r)
            tx_arr, rx_arr = array(m.tx_array), array(m.rx_array)
            src = sc._endpoints([tx], tx_arr, True, True)[:3]
            tgt = sc._endpoints(rxs, rx_arr, True, True)[:3]
            dr.make_opaque(*src, *tgt)
            self._groups.append(_LinkGroup(
                src=src, tgt=tgt, n=len(rxs), n_tx_ant=int(m.tx_array[0]) * int(m.tx_array[1]),
                n_rx_ant=int(m.rx_array[0]) * int(m.rx_array[1]),
                patterns=(tx_arr.antenna_pattern.patterns, rx_arr.antenna_pattern.patterns),
                # Sionna's cfr order [N, Nr, (tx=1), Nt, (time=1), K]
                meas_db=mi.Float64(power_db(m.csi.transpose(0, 2, 3, 1)).reshape(-1)),
                weight=len(rxs) / n_all,
                noise=None if m.noise_power is None else mi.Float64(np.repeat(
                    m.noise_power, m.csi[0].size))))
        # the scene's arrays: those of the first link (Sionna's own traces, visibility)
        sc.tx_array, sc.rx_array = array(self.links[0].tx_array), array(self.links[0].rx_array)
        lanes = self.settings.max_depth * self.settings.samples_per_src * max(
            g.n for g in self._groups)
        #: True: Sionna's deterministic candidate generator on every thread; False: the
        #: default one on one thread (see :data:`DETERMINISTIC_LANES`).
        self.deterministic_candidates = lanes <= DETERMINISTIC_LANES
        if not self.deterministic_candidates:
            log.info("calibrate: %d x %d rays x %d snapshots is more than the deterministic "
                     "candidate generator's %d lanes; the default generator runs on one "
                     "thread", self.settings.max_depth, self.settings.samples_per_src,
                     max(g.n for g in self._groups), DETERMINISTIC_LANES)
        self._solver = rt.PathSolver(deterministic=self.deterministic_candidates)
        self._solver.loop_mode = "evaluated"  # symbolic loops do not backpropagate
        self._at_initial = None  # (mismatch, gradient, model) at the scene's values
        self._visibility = None  # (values, result) of the last visibility()
        #: Keep the candidate chains of the next trace for the following ones (the
        #: image method and field calculator still run at the current geometry and
        #: materials): the sampled candidates change with a sub-millimetre move
        #: (lab: +1.5 dB^2 for 0.9 mm of one rack, a path no ray found any more),
        #: which stalls the line search. :meth:`fit` with ``trust`` sets it per round.
        #: The kept chains' reflection points stay where the first trace found them,
        #: a second-order approximation (1 cm / 1 deg later: median 0.01 dB, at most a
        #: few tenths of a dB in a fade); reported values are traced afresh.
        self.freeze_candidates = False
        self._candidates: list | None = None
        #: with ``settings.chains``: per link, its transmitter's chains and the
        #: (chain, receiver) pairs, enumerated at the first trace after
        #: :meth:`refresh_chains` (fit rounds, polish, hop, result call it)
        self._chains: list = [None] * len(self._groups)
        #: chain enumerations so far (each: every link's transmitter)
        self.chain_refreshes = 0
        #: Candidate buffer entries of every evaluation, per link (0: sized by the first).
        self.buffer_sizes = [0] * len(self._groups)
        #: Evaluations that found more candidates than the buffer held (it grew:
        #: Dr.Jit recompiled the evaluation's kernels once).
        self.buffer_regrows = 0
        #: The last :meth:`polish`: its first step's trials per parameter name and
        #: whether every step reached its last size (None before one ran).
        self.polish_trials: dict[str, list] = {}
        self.polish_converged: bool | None = None
        #: The last :meth:`hop`: per scanned parameter name, its scan and what was kept.
        self.hop_report: dict[str, dict] = {}
        self._freqs = mi.Float(self.links[0].subcarrier_offsets_hz)

    @property
    def buffer_size(self) -> int:
        """Candidate buffer entries of every evaluation, all links (0 before the first)."""
        return sum(self.buffer_sizes)

    # ------------------------------------------------------------------ helpers

    def _current(self, p: Parameter) -> float:
        if p.kind == "permittivity":
            return float(self._materials[p.target][0].relative_permittivity.numpy()[0])
        if p.kind == "conductivity":
            return float(self._materials[p.target][0].conductivity.numpy()[0])
        return 0.0  # pose offsets start at the loaded pose

    @staticmethod
    def _scale(p: Parameter, v: float) -> float:
        if p.scale is not None:
            if not p.scale > 0:
                raise CalibrationError(f"parameter {p.name}: scale must be > 0, got {p.scale}")
            return float(p.scale)
        if p.kind == "permittivity":
            return 0.1 * v
        if p.kind == "conductivity":
            return max(0.1 * v, 0.01)
        return 0.01 if p.kind in ("x", "y") else math.radians(1.0)

    def _apply(self, values: np.ndarray, grad: bool) -> list:
        """Write ``values`` into the scene; return the Dr.Jit variables, one per parameter."""
        dr, mi = self._dr, self._mi
        vars_ = []
        for v in values:
            x = dr.opaque(mi.Float, float(v))  # a literal would recompile every kernel
            if grad:
                dr.enable_grad(x)
            vars_.append(x)
        offsets: dict[str, dict] = {}
        for p, x in zip(self.params, vars_):
            if p.kind == "permittivity":
                for m in self._materials[p.target]:
                    m.relative_permittivity = x
            elif p.kind == "conductivity":
                for m in self._materials[p.target]:
                    m.conductivity = x
            else:
                offsets.setdefault(p.target, {})[p.kind] = x
        if offsets:
            params_mi = self.sc.mi_scene_params
            for obj, off in offsets.items():
                key, _, c, (rx, ry, z) = self._objects[obj]
                dx, dy = off.get("x", mi.Float(0.0)), off.get("y", mi.Float(0.0))
                yaw = off.get("yaw", mi.Float(0.0))
                cs, sn = dr.cos(yaw), dr.sin(yaw)
                cx, cy = float(c[0]), float(c[1])  # a NumPy scalar on the left drops AD
                pts = mi.Point3f(cx + cs * rx - sn * ry + dx, cy + sn * rx + cs * ry + dy, z)
                params_mi[key] = dr.ravel(pts)
            params_mi.update()
            self.sc.scene_geometry_updated()
        return vars_

    def _trace_db(self) -> list:
        """Model channel power in dB per link: Dr.Jit float64 arrays ``[N * Nr * Nt * K]``
        (the link's snapshots, antennas and subcarriers), each link traced on its own.

        Sionna's ``PathSolver`` stages (candidate generator, image method, field
        calculator) on a candidate buffer of *fixed* size, and the frequency
        response summed here instead of in Sionna's ``Paths``: the generator finds
        a different number of candidates whenever an object moves, and Sionna's
        kernels bake that number in (as ``Paths`` does the paths per link), so an
        evaluation at new poses recompiled ~12 kernels (13-16 s of LLVM on the
        lab, against ~1 s of work). The candidates are padded to
        :attr:`buffer_sizes` (grown by half when a trace finds more, counted in
        :attr:`buffer_regrows`); the padding is weighted out of the sum. The
        channel equals ``Paths.cfr`` of ``PathSolver`` with ``synthetic_array=True``
        (``tests/engine/calibration/test_calibrator.py``).
        """
        frozen = self._candidates if self.freeze_candidates else None
        out, kept = [], []
        for j, grp in enumerate(self._groups):
            h_db, buf = self._trace_link_db(j, grp, None if frozen is None else frozen[j])
            out.append(h_db)
            kept.append(buf)
        self._candidates = kept if self.freeze_candidates else None
        return out

    def refresh_chains(self) -> None:
        """New candidates at the next trace, at the geometry then: with
        ``settings.chains`` the transmitters' chains are enumerated again (the kept
        chains' reflection points stay where their rays found them: second order in a
        move), else the kept candidates of :attr:`freeze_candidates` are dropped."""
        self._chains = [None] * len(self._groups)
        self._candidates = None

    def _link_chains(self, j: int, grp) -> tuple:
        """Link ``j``'s chains (:func:`~isac_twin.raytrace.solver_core.chain_arrays`) and its
        (chain, receiver) pairs, padded to :attr:`buffer_sizes`: ``(chains, chain_idx,
        target_idx, pad)``, enumerated at the current geometry when refreshed."""
        from ..raytrace.chains import ChainStore
        from ..raytrace.planes import PlaneIndex
        from ..raytrace.solver_core import chain_arrays
        from ..raytrace.source_chains import MirrorFilter, shoot_chains

        if self._chains[j] is None:
            mi, s, sc = self._mi, self.settings, self.sc

            def points(p):
                return np.stack([np.asarray(c.numpy(), np.float64) for c in p], 1)

            src = points(grp.src[0])
            planes = PlaneIndex(sc.mi_scene)
            store = ChainStore(s.max_depth, planes)
            store.add_columns(shoot_chains(sc.mi_scene, planes, src, s.samples_per_src,
                                           s.max_depth, specular=True,
                                           refraction=s.refraction))
            per_target = MirrorFilter(planes, src, store.columns(),
                                      margin=CHAIN_FILTER_MARGIN)(points(grp.tgt[0]))
            n = sum(len(k) for k in per_target)
            if n > self.buffer_sizes[j]:
                if self.buffer_sizes[j]:
                    self.buffer_regrows += 1
                self.buffer_sizes[j] = max(1024, int(1.5 * n))
            size = self.buffer_sizes[j]
            ci = np.zeros(size, np.uint32)
            ti = np.zeros(size, np.uint32)
            if n:
                ci[:n] = np.concatenate(per_target)
                ti[:n] = np.repeat(np.arange(len(per_target), dtype=np.uint32),
                                   [len(k) for k in per_target])
            pad = np.ones(size, np.uint32)
            pad[:n] = 0
            arrays = [mi.UInt(ci), mi.UInt(ti), mi.UInt(pad)]
            self._dr.make_opaque(*arrays)
            self._chains[j] = (chain_arrays(store.columns(), s.max_depth), *arrays)
            if j == 0:
                self.chain_refreshes += 1
        return self._chains[j]

    def _trace_link_db(self, j: int, grp, buf):
        """One link of :meth:`_trace_db`: ``(power dB [N * Nr * Nt * K], candidates)``;
        ``buf``: that link's kept candidates (None: trace new ones)."""
        dr, mi = self._dr, self._mi
        s, sc, solver = self.settings, self.sc, self._solver
        (src, src_o, rel_tx), (tgt, tgt_o, rel_rx) = grp.src, grp.tgt
        if s.chains:
            from ..raytrace.solver_core import chain_candidates

            chains, ci, ti, pad = self._link_chains(j, grp)
            buf, unused = chain_candidates(sc.mi_scene, chains, ci, ti, src, tgt, s.max_depth,
                                           True, pad)
            return self._link_cfr_db(grp, buf, ~unused), None
        if buf is None:
            # the default generator keeps one candidate per chain of planes, whichever
            # ray's triangle wins a race on its hash table; with two threads the kept
            # triangle (and so the float32 image of a coplanar face) varied between
            # calls (lab: 3 different mismatches of 6 calls at the same values), so it
            # runs on one thread; the deterministic one runs on every thread
            threads = dr.thread_count()
            if not self.deterministic_candidates:
                dr.set_thread_count(1)
            try:
                buf = solver._candidate_generator(
                    mi_scene=sc.mi_scene, src_positions=src, tgt_positions=tgt,
                    samples_per_src=s.samples_per_src, max_num_paths_per_src=MAX_CANDIDATES,
                    max_depth=s.max_depth, los=True, specular_reflection=True,
                    diffuse_reflection=False, refraction=s.refraction, diffraction=False,
                    edge_diffraction=False, seed=s.seed)
                buf.schedule()
                dr.eval()
            finally:
                dr.set_thread_count(threads)
            buf.shrink()
        kept = buf
        n = int(buf.buffer_size)
        if n > self.buffer_sizes[j]:
            if self.buffer_sizes[j]:
                self.buffer_regrows += 1
            self.buffer_sizes[j] = max(1024, int(1.5 * n))
        size = self.buffer_sizes[j]
        buf = buf.gather(mi.UInt(np.concatenate([np.arange(n), np.zeros(size - n, int)])
                                 .astype(np.uint32)))
        used = mi.Bool(np.arange(size) < n)
        dr.make_opaque(used)
        return self._link_cfr_db(grp, buf, used), kept

    def _link_cfr_db(self, grp, buf, used):
        """Image method and field calculator on a link's candidates ``buf`` (``used``
        marks those that count: not padding, not a hidden line of sight), and
        its power in dB per snapshot, antenna pair and subcarrier (``[N * Nr * Nt * K]``,
        Dr.Jit float64)."""
        from sionna.rt.utils import map_angle_to_canonical_range

        from ..raytrace.solver_core import image_and_field

        dr, mi = self._dr, self._mi
        s, sc, solver = self.settings, self.sc, self._solver
        (src, src_o, rel_tx), (tgt, tgt_o, rel_rx) = grp.src, grp.tgt
        buf = image_and_field(solver, buf, sc.mi_scene, sc.wavelength, src, tgt,
                              samples_per_src=s.samples_per_src, src_o=src_o, tgt_o=tgt_o,
                              patterns=grp.patterns)
        size = dr.width(buf.valid)
        # H[t, r, s, k] = sum_p a_p exp(j 2pi/lambda (d_r . k_rx,p + d_s . k_tx,p))
        #                 exp(-j 2pi f_k tau_p), over the valid, unpadded p of target t
        n_rx, n_tx, k = grp.n_rx_ant, grp.n_tx_ant, len(self.links[0].subcarrier_offsets_hz)
        # (Paths.cir: the carrier's phase exp(-j 2pi f_c tau) first, as Sionna does)
        w = dr.select(buf.valid & used, mi.Float(1.0), mi.Float(0.0))
        a, tau, t = buf.a[0][0], buf.tau, buf.target_indices
        sn_c, cs_c = dr.sincos(map_angle_to_canonical_range(-2.0 * math.pi * sc.frequency * tau))
        a_re = (dr.real(a) * cs_c - dr.imag(a) * sn_c) * w
        a_im = (dr.real(a) * sn_c + dr.imag(a) * cs_c) * w
        k_tx, k_rx = buf.k_tx, buf.k_rx
        per = n_rx * n_tx * k
        j = dr.arange(mi.UInt, size * per)
        p, rem = j // per, j % per
        r, q = rem // (n_tx * k), rem % (n_tx * k)
        st, kk = q // k, q % k
        tp = dr.gather(mi.UInt, t, p)
        d_rx = dr.gather(mi.Point3f, rel_rx, tp * n_rx + r)
        d_tx = dr.gather(mi.Point3f, rel_tx, st)
        phase = (2.0 * math.pi / sc.wavelength) * (
            dr.dot(d_rx, dr.gather(mi.Vector3f, k_rx, p))
            + dr.dot(d_tx, dr.gather(mi.Vector3f, k_tx, p))) \
            - 2.0 * math.pi * dr.gather(mi.Float, self._freqs, kk) * dr.gather(mi.Float, tau, p)
        sn, cs = dr.sincos(phase)
        are, aim = dr.gather(mi.Float, a_re, p), dr.gather(mi.Float, a_im, p)
        out = tp * per + rem
        # summed in float64: the LLVM backend's atomic adds land in thread order, so a
        # float32 sum differed between calls at the same values (lab: 4 losses of 6
        # within 7e-7, gradients 0.3 % apart), which steered the line search apart
        h_re = dr.zeros(mi.Float64, grp.n * per)
        h_im = dr.zeros(mi.Float64, grp.n * per)
        dr.scatter_add(h_re, mi.Float64(are * cs - aim * sn), out)
        dr.scatter_add(h_im, mi.Float64(are * sn + aim * cs), out)
        pw = h_re * h_re + h_im * h_im
        if grp.noise is not None:  # what a noisy estimate's power is on average
            pw = pw + grp.noise
        return 10.0 * dr.log(pw + POWER_FLOOR) / math.log(10.0)

    def _trace(self):
        s = self.settings
        return self._solver(self.sc, max_depth=s.max_depth, samples_per_src=s.samples_per_src,
                            synthetic_array=True, los=True, specular_reflection=True,
                            diffuse_reflection=False, refraction=s.refraction,
                            diffraction=False, seed=s.seed)

    # ------------------------------------------------------------------ API

    def visibility(self, values=None) -> dict[str, dict]:
        """How much of the measured channel each parameter's target touches, from one
        trace (no gradients) at ``values`` (physical units, ``[P]``; default the
        scene's values).

        A path touches a material when one of its interactions (reflection or
        refraction) is on an object of that material, and an object when one is on
        that object. Its power is ``|a|^2`` summed over the antenna pairs.

        Returns:
            ``target -> {"paths": [N] paths touching it per snapshot, "power_share":
            [N] their share of the snapshot's total path power (0..1),
            "strongest_db": [N] the strongest such path relative to the snapshot's
            strongest path, dB (-inf without one)}``, one entry per material or
            object named by a parameter.
        """
        dr = self._dr
        values = np.array(self.initial if values is None else values, float).reshape(-1)
        # the same values twice (calibrate_run: the objects' paths and the materials'
        # observability at the fit): one trace
        if self._visibility is not None and np.array_equal(self._visibility[0], values):
            return self._visibility[1]
        self._apply(values, False)
        paths = self._trace()
        objs = np.asarray(paths.objects.numpy())  # [D, N, T, P] (synthetic array)
        a_re, a_im = (np.asarray(dr.detach(t).numpy()) for t in paths.a)
        pw = (a_re ** 2 + a_im ** 2).sum(axis=(1, 3))  # [N, Nr, T, Nt, P] -> [N, T, P]
        valid = np.asarray(paths.valid.numpy()).reshape(pw.shape)
        # every link's transmitter was traced to every snapshot: keep the measured pairs
        # (the scene's arrays are the first link's: the same gain on every path of a pair)
        snap = np.arange(pw.shape[0])
        link = np.concatenate([np.full(g.n, j) for j, g in enumerate(self._groups)])
        pw, valid = pw[snap, link], valid[snap, link]  # [N, P]
        pw = np.where(valid, pw, 0.0)
        objs = objs.reshape(objs.shape[0], len(snap), len(self._groups), -1)[:, snap, link]
        total = pw.sum(axis=1)
        top = pw.max(axis=1)
        ids: dict[str, set[int]] = {}
        for p in self.params:
            if p.target in ids:
                continue
            if p.kind in MATERIAL_KINDS:
                mats = {id(m) for m in self._materials[p.target]}
                ids[p.target] = {int(o.object_id) for o in self.sc.objects.values()
                                 if id(o.radio_material) in mats}
            else:
                ids[p.target] = {int(self.sc.objects[p.target].object_id)}
        out = {}
        for target, oids in ids.items():
            hit = np.isin(objs, list(oids)).any(axis=0) & valid  # [N, P]
            share = np.where(total > 0, (pw * hit).sum(axis=1) / np.where(total > 0, total, 1),
                             0.0)
            strongest = np.where(hit, pw, 0.0).max(axis=1)
            with np.errstate(divide="ignore"):
                rel = np.where(strongest > 0, 10 * np.log10(strongest / np.where(top > 0, top, 1)),
                               -np.inf)
            out[target] = {"paths": hit.sum(axis=1).astype(int), "power_share": share,
                           "strongest_db": rel}
        self._visibility = (values, out)
        return out

    def evaluate(self, values, grad: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
        """Mismatch at ``values`` (physical units, ``[P]``).

        Returns:
            ``(mismatch dB^2, gradient [P] in dB^2 per unit, model power [N, K, Nr, Nt]
            dB)``; the model is a list of those, one per link, when the calibrator was
            given a list of measurements.
        """
        dr = self._dr
        t0 = time.perf_counter()
        values = np.asarray(values, float).reshape(-1)
        vars_ = self._apply(values, grad)
        models_db = self._trace_db()
        loss = None
        for grp, model_db in zip(self._groups, models_db):
            diff = model_db - grp.meas_db
            # each snapshot counts the same (one link: weight 1, the mean itself)
            term = grp.weight * dr.mean(diff * diff)
            loss = term if loss is None else loss + term
        g = np.zeros(len(values))
        if grad:
            dr.eval(loss)  # the forward pass on every thread
            # The backward pass on one thread: it accumulates the gradients with
            # float32 atomic adds, which on two threads land in timing order, so
            # the gradient at the same values differed in its last bits between
            # calls; L-BFGS-B amplified that into different fits of the same lap
            # (the tables' permittivity 3.1 %, 6.0 % and 20.6 % off in three runs).
            threads = dr.thread_count()
            dr.set_thread_count(1)
            try:
                # at some bounds (conductivity 0) Sionna's graph no longer depends
                # on a parameter: its gradient is then 0, not an error
                dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
                g = np.array([float(dr.grad(x)[0]) for x in vars_])
            finally:
                dr.set_thread_count(threads)
        k = len(self._freqs)
        models = [np.array(dr.detach(m).numpy(), float)
                  .reshape(grp.n, grp.n_rx_ant, grp.n_tx_ant, k).transpose(0, 3, 1, 2)
                  for grp, m in zip(self._groups, models_db)]
        out = float(loss[0]), g, models[0] if self._one_link else models
        if grad:  # leave the scene at values, detached from the graph (a BVH rebuild)
            self._apply(values, False)
        self.evaluations += 1
        (self.step_seconds if grad else self.forward_seconds).append(time.perf_counter() - t0)
        return out

    def scan(self, index: int, values, start=None) -> np.ndarray:
        """Mismatch (dB^2, ``[S]``) with parameter ``index`` set to each of ``values``
        (physical units, ``[S]``, clipped to its bounds) and the others at ``start``
        (default the scene's values); no gradients.

        A slab's reflection is nearly periodic in ``sqrt(permittivity)`` with period
        ``wavelength / (2 thickness)`` (multiple reflections inside it), so over a
        narrow band the mismatch has one local minimum per period: scan permittivity
        on a grid finer than that before :meth:`fit`.
        """
        base = np.array(self.initial if start is None else start, float)
        lo, hi = self.params[index].limits
        out = []
        for v in np.clip(np.asarray(values, float).reshape(-1), lo, hi):
            x = base.copy()
            x[index] = v
            out.append(self.evaluate(x, grad=False)[0])
        return np.array(out)

    def polish(self, start, free, *, steps: tuple[float, float] = POLISH_STEPS,
               max_evaluations: int = 400,
               refresh: bool = True) -> tuple[np.ndarray, float, int]:
        """Coordinate pattern search from ``start`` (physical units, ``[P]``) over the
        parameters ``free`` (indices), no gradients: each trace with fresh candidates,
        or with ``settings.chains`` the chains enumerated at the start and again after
        every sweep that moved something (``refresh=False``: the chains kept so far).

        For each free parameter in turn: try ``+-step`` (in its ``scale``); keep a move
        that lowers the mismatch, else halve its step; until every step is below
        ``steps[1]`` (``steps[0]`` first) or ``max_evaluations`` traces. The mismatch
        jumps wherever a path appears or disappears (a reflection point leaves its
        face, a candidate ray misses it), which stops L-BFGS-B's line search (lab:
        Rack_2's yaw left 0.9 deg off, where 1 deg further along lowered the mismatch
        from 1.29 to 0.83 dB^2); a search that compares traced values is not stopped.

        Returns:
            ``(values [P], mismatch dB^2, traces)``; :attr:`polish_converged` says whether
            every step reached ``steps[1]`` (else ``max_evaluations`` ended it).
        """
        x = np.clip(np.asarray(start, float).reshape(-1).copy(),
                    [p.limits[0] for p in self.params], [p.limits[1] for p in self.params])
        free = [int(i) for i in free]
        if not all(0 <= i < len(x) for i in free):
            raise CalibrationError(f"polish: free must name parameters 0..{len(x) - 1}, "
                                   f"got {free!r}")
        step = {i: steps[0] * self.scales[i] for i in free}
        if refresh:  # (else the chains kept so far: the hop's searches)
            self.refresh_chains()
        f = self.evaluate(x, grad=False)[0]
        # name -> [[move (physical units), mismatch change dB^2], ...] of the first step
        self.polish_trials = {self.params[i].name: [] for i in free}
        n = n_at = 1
        at = x.copy()  # where the chains were enumerated
        stale = refresh and self.settings.chains  # (else nothing to refresh)

        def active():
            return any(step[i] >= steps[1] * self.scales[i] * (1 - 1e-9) for i in free)

        while n < max_evaluations and (active() or (stale and not np.array_equal(x, at))):
            if stale and not np.array_equal(x, at) and (
                    n - n_at >= POLISH_REFRESH_TRACES or not active()):
                # sweeps moved something: the chains of where they ended (the kept
                # chains' reflection points lag the moved objects; lab: the hop's
                # fresh chains traced the polish's end at another mismatch). Not
                # after every such sweep: late in a search a sweep is a few traces
                # of the coordinates still searched, and an enumeration (~1 s on the
                # lab) cost more than they did
                self.refresh_chains()
                f, at, n_at = self.evaluate(x, grad=False)[0], x.copy(), n
                n += 1
                if not active():  # the end, on fresh chains: one more sweep there
                    step = {i: steps[1] * self.scales[i] for i in free}
            for i in free:
                if step[i] < steps[1] * self.scales[i] * (1 - 1e-9) or n >= max_evaluations:
                    continue
                lo, hi = self.params[i].limits
                for sgn in (1.0, -1.0):
                    y = x.copy()
                    y[i] = float(np.clip(x[i] + sgn * step[i], lo, hi))
                    if y[i] == x[i]:
                        continue
                    fy = self.evaluate(y, grad=False)[0]
                    n += 1
                    if step[i] == steps[0] * self.scales[i]:
                        self.polish_trials[self.params[i].name].append(
                            [float(y[i] - x[i]), float(fy - f)])
                    if fy < f:
                        x, f = y, fy
                        break
                else:
                    step[i] /= 2.0
        self.polish_converged = not active()
        self.evaluate(x, grad=False)  # leave the scene there
        log.info("calibrate: polish %d traces -> %.5g dB^2", n, f)
        return x, f, n

    def hop(self, start, free, *, unseen=(), span: tuple[float, float] = HOP_SPAN,
            per_wavelength: int = HOP_PER_WAVELENGTH,
            steps: tuple[float, float] = POLISH_STEPS) -> tuple[np.ndarray, float, int]:
        """Move x/y offsets and yaws into a lower half-wavelength basin.

        From ``start`` (physical units, ``[P]``), for each x, y or yaw parameter of
        ``free`` (indices; others are skipped) in turn: trace (no gradients; the chains
        of the start, with ``settings.chains``, else fresh candidates) its value shifted
        by every multiple of ``wavelength / per_wavelength`` between ``span[0]`` and
        ``span[1]`` wavelengths to either side (a yaw: turns that move the object's
        farthest vertex so far, from one step on) inside its bounds; take the lowest
        local minimum of that scan other than the current value's basin; if it is
        below :data:`HOP_SLACK` times the current mismatch, search it (:meth:`polish`
        on that coordinate alone, from half a scan step down to ``steps[1]``). Then,
        the best first, a searched basin that gains more than :data:`HOP_GAIN` of the
        mismatch (:data:`HOP_GAIN_UNSEEN` for a parameter of ``unseen``, indices the
        start gradient did not see) and :data:`HOP_MIN_GAIN_DB2` is traced with its own
        chains and kept if it still does (searched again from the values so far once
        another was kept).

        A gradient fit and :meth:`polish` end in the basin they start in; the
        magnitude mismatch repeats about every half wavelength of a shift normal to a
        reflecting face, so an object that starts more than ~1/4 wavelength away (the
        lab's Table_2: 6.9 cm at 12.5 cm wavelength) ends a period off, where the
        truth's basin is lower (0.28 against 0.39 dB^2 there).

        Returns:
            ``(values [P], mismatch dB^2, traces)``; :attr:`hop_report` lists, per
            scanned parameter name, the shifts (m; rad for a yaw), their mismatch, the
            mismatch before its scan, the shift searched, where that search ended and
            whether it was kept.
        """
        x = np.asarray(start, float).reshape(-1).copy()
        free = [int(i) for i in free]
        unseen = {int(i) for i in unseen}
        if not all(0 <= i < len(x) for i in [*free, *unseen]):
            raise CalibrationError(f"hop: free and unseen must name parameters "
                                   f"0..{len(x) - 1}, got {free!r} and {sorted(unseen)!r}")
        step = float(self.sc.wavelength[0]) / per_wavelength
        found = []  # (mismatch, index, value) of the searched basins that gained
        k = np.arange(int(math.ceil(span[0] * per_wavelength)),
                      int(math.floor(span[1] * per_wavelength)) + 1)
        k = np.concatenate([-k[::-1], [0], k])
        # a yaw's ring starts at one step: a turn has nearer basins too (lab: Chair_2
        # at -0.87 deg where the truth is +0.89, 1.76 deg or ~1 cm at its corners away)
        k_yaw = np.arange(1, int(math.floor(span[1] * per_wavelength)) + 1)
        k_yaw = np.concatenate([-k_yaw[::-1], [0], k_yaw])
        self.refresh_chains()
        f = self.evaluate(x, grad=False)[0]
        n = 1
        self.hop_report = {}
        steps_of = {}
        for i in free:
            p = self.params[i]
            if p.kind in ("x", "y"):
                steps_of[i] = step
            elif p.kind == "yaw":
                # a turn moves the object's farthest vertex by radius x angle: the same
                # shifts there (lab: Table_1's yaw 3.6-3.9 deg off, a basin away)
                _, v, c, _ = self._objects[p.target]
                steps_of[i] = step / float(np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]).max())
            else:
                continue
            lo, hi = p.limits
            ring = k_yaw if p.kind == "yaw" else k
            grid = np.unique(np.clip(x[i] + steps_of[i] * ring, lo, hi))
            at = int(np.argmin(np.abs(grid - x[i])))
            grid[at] = x[i]
            fs = np.insert(self.scan(i, np.delete(grid, at), x), at, f)
            n += len(grid) - 1
            # the current basin: the points rising away from the current value (the
            # scan skips the shifts within span[0])
            own = {at}
            for d in (-1, 1):
                j = at
                while 0 <= j + d < len(grid) and fs[j + d] >= fs[j]:
                    j += d
                    own.add(j)
            others = [j for j in local_minima(fs) if j not in own]
            entry = {"shifts_m": (grid - x[i]).tolist(), "mismatch_db2": fs.tolist(),
                     "mismatch_before_db2": float(f), "tried_m": None,
                     "mismatch_after_db2": None, "kept": False}
            if others and fs[others[0]] < HOP_SLACK * f:
                j = others[0]
                y = x.copy()
                y[i] = grid[j]
                z, fz, m = self.polish(y, [i], steps=(0.5 * steps_of[i] / self.scales[i],
                                                      steps[1]), refresh=False)
                n += m
                entry.update(tried_m=float(z[i] - x[i]), mismatch_after_db2=float(fz))
                if f - fz > max(self._hop_gain(i, unseen) * f, HOP_MIN_GAIN_DB2):
                    found.append((fz, i, float(z[i])))
            self.hop_report[p.name] = entry
        # the best first: the searches all started from the same values, and a hop kept
        # early took the gain of a later, larger one (lab: Rack_2's y moved 8.9 cm
        # while Table_2's y was a period off, then Table_2's hop could not undo it)
        f0, x0 = f, x.copy()
        for fz, i, zi in sorted(found):
            y = x.copy()
            y[i] = zi
            if not np.array_equal(x, x0):  # another hop was kept: search again from it
                y, fz, m = self.polish(y, [i], steps=(0.25 * steps_of[i] / self.scales[i],
                                                      steps[1]), refresh=False)
                n += m
            self.refresh_chains()  # its own chains there
            fz = self.evaluate(y, grad=False)[0]
            n += 1
            entry = self.hop_report[self.params[i].name]
            entry.update(tried_m=float(y[i] - x0[i]), mismatch_after_db2=float(fz))
            if f - fz > max(self._hop_gain(i, unseen) * f, HOP_MIN_GAIN_DB2):
                x, f = y, fz
                entry["kept"] = True
            self.refresh_chains()
        self._apply(x, False)  # leave the scene there (no trace: fresh chains follow)
        log.info("calibrate: hop %d traces -> %.5g dB^2", n, f)
        return x, f, n

    @staticmethod
    def _hop_gain(i: int, unseen) -> float:
        return HOP_GAIN_UNSEEN if i in unseen else HOP_GAIN

    def fit(self, *, max_steps: int = 30, ftol: float = 1e-7, gtol: float = 1e-6,
            start=None, free=None, trust: float | None = None) -> CalibrationResult:
        """Fit by L-BFGS-B inside the bounds.

        Args:
            start: ``[P]`` values to start from (physical units; e.g. the best of a
                :meth:`scan`); default the scene's values. ``initial`` in the result
                stays the scene's values.
            free: indices of the parameters to fit (default all); the others stay at
                ``start`` (e.g. materials held while poses are fitted).
            trust: None, or fit in rounds, each inside a box of +-``trust`` typical
                changes (``scale``) about the round's start, a new round from where a
                round ended while a round lowers the mismatch by more than
                :data:`ROUND_GAIN` of it (``max_steps`` iterations in all).
            max_steps: most optimiser iterations.
            ftol: stop when the relative mismatch change per step is below this.
            gtol: stop when the projected gradient (per ``scale``) is below this, dB^2.

        Returns:
            :class:`CalibrationResult`; the scene is left at the fitted values.
        """
        from scipy.optimize import minimize

        x0 = self.initial if start is None else np.asarray(start, float).reshape(-1)
        if x0.shape != self.initial.shape:
            raise CalibrationError(f"fit: start must have {len(self.initial)} values, "
                                   f"got {x0.shape}")
        x0 = np.clip(x0, [p.limits[0] for p in self.params], [p.limits[1] for p in self.params])
        idx = np.arange(len(x0)) if free is None else np.unique(np.asarray(free, int))
        if len(idx) == 0 or idx.min() < 0 or idx.max() >= len(x0):
            raise CalibrationError(f"fit: free must name parameters 0..{len(x0) - 1}, "
                                   f"got {free!r}")
        sc = self.scales[idx]
        history: list[float] = []

        def values(u):
            x = x0.copy()
            x[idx] += u * sc
            return x

        def fun(u):
            x = values(u)
            f, g, model = self.evaluate(x)
            history.append(f)
            if self._at_initial is None and np.array_equal(x, self.initial):
                self._at_initial = (f, g, model)
            log.info("calibrate: step %d mismatch %.5g dB^2 at %s", len(history), f,
                     np.round(x, 6).tolist())
            return f, g[idx] * sc

        lo = np.array([(self.params[i].limits[0] - x0[i]) / s for i, s in zip(idx, sc)])
        hi = np.array([(self.params[i].limits[1] - x0[i]) / s for i, s in zip(idx, sc)])
        if trust is None:
            res = minimize(fun, np.zeros(len(idx)), jac=True, method="L-BFGS-B",
                           bounds=list(zip(lo, hi)),
                           options={"maxiter": max_steps, "ftol": ftol, "gtol": gtol})
            u, rounds = res.x, 1
        else:
            # rounds of L-BFGS-B in a box of +-trust (scaled units) about the round's
            # start, a new round (fresh candidates and curvature memory) while a round
            # lowers the mismatch by more than ROUND_GAIN. Unbounded, L-BFGS-B's
            # quasi-Newton trial steps jump several cm, across the half-wavelength
            # basins of a magnitude mismatch (lab: trial mismatches of 9-10 dB^2 from
            # 7.6, then a stall at 7.56 after 52 evaluations)
            u, steps_left, rounds, best = np.zeros(len(idx)), max_steps, 0, np.inf
            while steps_left > 0:
                self.freeze_candidates = True  # this round's candidates or chains
                self.refresh_chains()
                res = minimize(fun, u, jac=True, method="L-BFGS-B",
                               bounds=list(zip(np.maximum(lo, u - trust),
                                               np.minimum(hi, u + trust))),
                               options={"maxiter": steps_left, "ftol": ftol, "gtol": gtol,
                                        "maxls": MAX_LINE_SEARCH})
                rounds += 1
                steps_left -= max(1, int(res.nit))
                gain = best - float(res.fun)
                u, best = res.x, min(best, float(res.fun))
                if gain <= ROUND_GAIN * abs(best):
                    break
            self.freeze_candidates, self._candidates = False, None
        converged, message = bool(res.success), str(res.message)
        if not converged and message.startswith("ABNORMAL") and _flat_tail(history):
            # the line search's trial steps all gave the best value: no step it
            # can take changes the traced geometry's mismatch (float32 vertices),
            # a minimum to that resolution (a noise-free room: 1e-9 dB^2)
            converged = True
            message += (f" at the float32 floor: the last {FLAT_TAIL} evaluations equal "
                        f"the best mismatch, {min(history):.3g} dB^2")
        return self.result(values(u), converged=converged,
                           message=message + (f" ({rounds} trust-box rounds)" if trust else ""),
                           history=history)

    def result(self, final, *, converged: bool, message: str,
               history: list[float] | None = None) -> CalibrationResult:
        """The :class:`CalibrationResult` of ``final`` (physical units, ``[P]``), traced
        afresh and reported against the scene's values; leaves the scene at ``final``."""
        final = np.asarray(final, float).reshape(-1)
        if self._at_initial is None:  # report against the scene's values
            self._at_initial = self.evaluate(self.initial)
        first = dict(zip(("f", "g", "model"), self._at_initial))
        self.refresh_chains()  # the final values' own chains
        f_final, _, model = self.evaluate(final, grad=False)  # leaves the scene there
        def rms(models):  # per snapshot, the links' snapshots one after the other
            models = [models] if self._one_link else models
            return np.concatenate([np.sqrt(np.mean((mod - power_db(m.csi)) ** 2,
                                                   axis=(1, 2, 3)))
                                   for mod, m in zip(models, self.links)])

        residual, residual0 = rms(model), rms(first["model"])
        names = [p.name for p in self.params]
        return CalibrationResult(
            names=names, initial=self.initial.copy(), final=final, gradient_initial=first["g"],
            unobserved=unobserved(first["g"] * self.scales, names),
            mismatch_initial=first["f"], mismatch_final=f_final, residual_db=residual,
            converged=bool(converged), message=message, evaluations=self.evaluations,
            seconds_per_step=float(np.mean(self.step_seconds)) if self.step_seconds else 0.0,
            history=list(history or []),
            residual_db_initial=residual0)
