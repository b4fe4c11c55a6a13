"""Conformance checks every tracer backend must pass.

``check_tracer(tracer, scene)`` calls the backend and checks, independently of
it (geometry comes from Mitsuba ray casts and analytic formulas):

* ``shapes``: every array has the documented shape and dtype, values are finite,
  interaction codes are Sionna ``InteractionType`` codes with trailing NONE padding,
  paths are sorted by delay;
* ``units``: delays are in seconds (``d/c <= tau < 1 ms``), zenith in ``[0, pi]``,
  azimuth in ``[-pi, pi]``;
* ``los``: for every link whose segment Mitsuba finds unobstructed there is a
  LOS path with ``tau = d / c`` (rel. 1e-6), free-space gain
  ``|a|^2 = (lambda / 4 pi d)^2`` (rel. 1e-3, upright arrays), departure
  direction towards the receiver and arrival direction towards the
  transmitter (1e-3 rad);
* ``reciprocity``: the swapped link (rx -> tx) has the same LOS delay and
  gain magnitude and swapped angles;
* ``determinism``: two calls with the same poses give the same paths;
* ``errors``: a NaN pose and a position outside the scene raise ``ValueError``
  naming the device.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .base import (
    INTERACTION_DIFFRACTION,
    INTERACTION_DIFFUSE,
    INTERACTION_NONE,
    INTERACTION_REFRACTION,
    INTERACTION_SPECULAR,
    SPEED_OF_LIGHT,
    DevicePose,
    Link,
    LinkPaths,
    device_poses,
    resolve_links,
)
from .raw import find_repeats, match_paths

_CODES = {INTERACTION_NONE, INTERACTION_SPECULAR, INTERACTION_DIFFUSE, INTERACTION_REFRACTION,
          INTERACTION_DIFFRACTION}
_ANGLE_TOL = 1e-3
_DELAY_RTOL = 1e-6


@dataclass
class CheckResult:
    name: str
    passed: bool
    detail: str = ""


@dataclass
class ConformanceReport:
    """Outcome of :func:`check_tracer`."""

    results: list[CheckResult] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(r.passed for r in self.results)

    @property
    def failures(self) -> list[CheckResult]:
        return [r for r in self.results if not r.passed]

    def add(self, name: str, ok: bool, detail: str = "") -> None:
        self.results.append(CheckResult(name, bool(ok), detail))

    def __str__(self) -> str:
        return "\n".join(f"{'PASS' if r.passed else 'FAIL'} {r.name}"
                         + (f": {r.detail}" if r.detail else "") for r in self.results)


def _r_hat(theta, phi) -> np.ndarray:
    st = np.sin(theta)
    return np.array([st * np.cos(phi), st * np.sin(phi), np.cos(theta)])


def _angle(u, v) -> float:
    c = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    return math.acos(max(-1.0, min(1.0, c)))


def line_of_sight(scene, a, b) -> bool:
    """Whether the segment ``a``-``b`` (m) is unobstructed (Mitsuba ray test)."""
    import mitsuba as mi

    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    length = float(np.linalg.norm(d))
    ray = mi.Ray3f(mi.Point3f(*(float(x) for x in a)),
                   mi.Vector3f(*(float(x) for x in d / length)))
    ray.maxt = length * (1 - 1e-6)
    return not bool(scene.sionna.mi_scene.ray_test(ray)[0])


def scene_edges(mi_scene) -> np.ndarray:
    """Every triangle edge of the Mitsuba scene's meshes, ``[E, 2, 3]`` m (float64)."""
    out = []
    for s in mi_scene.shapes():
        if not s.is_mesh() or s.face_count() == 0:
            continue
        v = np.asarray(s.vertex_positions_buffer().numpy(), np.float64).reshape(-1, 3)
        f = np.asarray(s.faces_buffer().numpy(), np.int64).reshape(-1, 3)
        for i, j in ((0, 1), (1, 2), (2, 0)):
            out.append(np.stack([v[f[:, i]], v[f[:, j]]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2, 3))


#: :func:`grazing`: an interaction this close to a triangle edge, m.
GRAZING_TOL_M = 1e-4


def grazing(interactions, vertices, edges: np.ndarray, tol: float = GRAZING_TOL_M
            ) -> np.ndarray:
    """Which paths touch an edge: an interaction point within ``tol`` of a triangle
    edge (:func:`scene_edges`). Whether a ray finds such a path is float rounding
    (lab machines: a -19 dB path refracted exactly at a table top's edge, kept by
    chain reuse's image method and missed by shoot-and-bounce at 10^7 rays on an
    AVX-512 CPU, found by both on AVX2), so tracers may differ on it; a conformance
    check reports it apart from a path one tracer invented.

    Args:
        interactions: ``[P, D]`` int (0: none). vertices: ``[P, D, 3]`` m.
        edges: ``[E, 2, 3]`` m.

    Returns:
        ``[P]`` bool.
    """
    inter = np.asarray(interactions).reshape(len(interactions), -1)
    verts = np.asarray(vertices, np.float64).reshape(len(interactions), -1, 3)
    a, b = edges[:, 0], edges[:, 1]
    ab = b - a
    den = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
    out = np.zeros(len(inter), bool)
    for p, d in zip(*np.nonzero(inter)):
        q = verts[p, d]
        t = np.clip(np.einsum("ij,ij->i", q - a, ab) / den, 0.0, 1.0)
        out[p] |= bool(np.min(np.linalg.norm(a + t[:, None] * ab - q, axis=1)) <= tol)
    return out


def check_shapes(lp: LinkPaths) -> list[str]:
    """Problems with the shapes, dtypes, value ranges and order of ``lp``."""
    errs = []
    L = lp.tau.shape[0] if lp.tau.ndim == 1 else -1
    if L < 0:
        return [f"tau has shape {lp.tau.shape}, expected [L]"]
    for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r"):
        v = getattr(lp, k)
        if v.shape != (L,):
            errs.append(f"{k} has shape {v.shape}, expected ({L},)")
        if not np.all(np.isfinite(v)):
            errs.append(f"{k} has non-finite values")
    if not np.iscomplexobj(lp.a):
        errs.append(f"a has dtype {lp.a.dtype}, expected complex")
    if lp.pol is not None:  # optional: the polarization transfer matrices
        pol = np.asarray(lp.pol)
        if pol.shape != (L, 2, 2):
            errs.append(f"pol has shape {pol.shape}, expected ({L}, 2, 2)")
        elif not np.iscomplexobj(pol) or not np.all(np.isfinite(pol)):
            errs.append(f"pol must be finite complex, got dtype {pol.dtype}")
    for k in ("tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r"):
        if not np.issubdtype(getattr(lp, k).dtype, np.floating):
            errs.append(f"{k} has dtype {getattr(lp, k).dtype}, expected float")
    if lp.interactions.ndim != 2 or lp.interactions.shape[0] != L:
        errs.append(f"interactions has shape {lp.interactions.shape}, expected [{L}, D]")
    elif not np.issubdtype(lp.interactions.dtype, np.integer):
        errs.append(f"interactions has dtype {lp.interactions.dtype}, expected integer")
    else:
        D = lp.interactions.shape[1]
        if lp.vertices.shape != (L, D, 3):
            errs.append(f"vertices has shape {lp.vertices.shape}, expected ({L}, {D}, 3)")
        bad = set(np.unique(lp.interactions).tolist()) - _CODES
        if bad:
            errs.append(f"unknown interaction codes {sorted(bad)}")
        used = lp.interactions != INTERACTION_NONE
        if np.any(np.diff(used.astype(int), axis=1) > 0):
            errs.append("NONE padding is not trailing")
    for k in ("tx_position", "rx_position", "tx_orientation", "rx_orientation"):
        if np.asarray(getattr(lp, k)).shape != (3,):
            errs.append(f"{k} must have shape (3,)")
    if L:
        if np.any(np.diff(lp.tau) < 0):
            errs.append("paths are not sorted by delay")
        d = lp.distance
        if lp.tau.min() < d / SPEED_OF_LIGHT * (1 - 1e-5):
            errs.append(f"a delay {lp.tau.min():.4g} s is shorter than distance/c")
        if lp.tau.max() >= 1e-3:
            errs.append(f"delay {lp.tau.max():.4g} s >= 1 ms: units are not seconds?")
        for k in ("theta_t", "theta_r"):
            v = getattr(lp, k)
            if v.min() < -1e-6 or v.max() > math.pi + 1e-6:
                errs.append(f"{k} outside [0, pi]")
        for k in ("phi_t", "phi_r"):
            v = getattr(lp, k)
            if v.min() < -math.pi - 1e-6 or v.max() > math.pi + 1e-6:
                errs.append(f"{k} outside [-pi, pi]")
    return errs


def check_los(lp: LinkPaths, *, gain: bool = True) -> list[str]:
    """Problems with the LOS path of an unobstructed link."""
    idx = np.flatnonzero(lp.is_los)
    if idx.size != 1:
        return [f"{lp.tx}->{lp.rx}: expected exactly one LOS path, found {idx.size}"]
    i = idx[0]
    errs = []
    d = lp.distance
    want = d / SPEED_OF_LIGHT
    if abs(lp.tau[i] - want) > _DELAY_RTOL * want:
        errs.append(f"{lp.tx}->{lp.rx}: LOS delay {lp.tau[i]:.9e} s != d/c {want:.9e} s "
                    f"(rel. {abs(lp.tau[i] / want - 1):.2e})")
    k = (np.asarray(lp.rx_position) - lp.tx_position) / d
    at = _angle(_r_hat(lp.theta_t[i], lp.phi_t[i]), k)
    ar = _angle(_r_hat(lp.theta_r[i], lp.phi_r[i]), -k)
    if at > _ANGLE_TOL:
        errs.append(f"{lp.tx}->{lp.rx}: LOS departure direction is {at:.2e} rad off the receiver")
    if ar > _ANGLE_TOL:
        errs.append(f"{lp.tx}->{lp.rx}: LOS arrival direction is {ar:.2e} rad off the transmitter")
    if gain:
        lam = SPEED_OF_LIGHT / lp.frequency_hz
        friis = (lam / (4 * math.pi * d)) ** 2
        p = float(np.abs(lp.a[i]) ** 2)
        if abs(p / friis - 1) > 1e-3:
            errs.append(f"{lp.tx}->{lp.rx}: LOS gain {p:.6e} != Friis {friis:.6e} "
                        f"(rel. {abs(p / friis - 1):.2e})")
    return errs


def _same(a: LinkPaths, b: LinkPaths) -> str:
    if a.num_paths != b.num_paths:
        return f"{a.num_paths} vs {b.num_paths} paths"
    for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r", "interactions"):
        x, y = getattr(a, k), getattr(b, k)
        if not np.allclose(x, y, rtol=1e-6, atol=0):
            return f"{k} differs (max abs diff {np.max(np.abs(x - y)):.3g})"
    return ""


def check_tracer(tracer, scene, poses: Mapping[str, DevicePose] | None = None,
                 links: Iterable[Link] | None = None, *, check_errors: bool = True,
                 raise_on_failure: bool = False) -> ConformanceReport:
    """Run the conformance checks on ``tracer`` for ``scene``.

    Args:
        tracer: a :class:`~isac_twin.raytrace.base.Tracer`.
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene`; at least one link should be
            unobstructed (an "open configuration") for the LOS checks.
        poses: device poses (default: from the config).
        links: links to check (default: the config's links).
        check_errors: also check that bad poses raise ``ValueError``.
        raise_on_failure: raise ``AssertionError`` listing the failures.
    """
    rep = ConformanceReport()
    poses = dict(poses or device_poses(scene.config))
    links = resolve_links(scene.config, links)
    res = tracer(scene, poses, links)
    rep.add("links", set(res) == set(links),
            f"returned {sorted(res)}, requested {sorted(links)}")
    errs = [f"{lk[0]}->{lk[1]}: {e}" for lk in links if lk in res for e in check_shapes(res[lk])]
    rep.add("shapes+units", not errs, "; ".join(errs))

    open_links = [lk for lk in links if lk in res
                  and line_of_sight(scene, res[lk].tx_position, res[lk].rx_position)]
    if not open_links:
        rep.add("los", False, "no unobstructed link to check (use an open configuration)")
    else:
        errs = []
        for lk in open_links:
            lp = res[lk]
            upright = not np.any(np.abs(np.r_[lp.tx_orientation[:2], lp.rx_orientation[:2]]) > 0)
            errs += check_los(lp, gain=upright)
        rep.add("los", not errs, "; ".join(errs) or f"{len(open_links)} open link(s)")

        tx, rx = open_links[0]
        try:
            back = tracer(scene, poses, [(rx, tx)])[(rx, tx)]
            fwd = res[(tx, rx)]
            i, j = np.flatnonzero(fwd.is_los), np.flatnonzero(back.is_los)
            errs = []
            if i.size != 1 or j.size != 1:
                errs.append("LOS path missing in one direction")
            else:
                i, j = i[0], j[0]
                if abs(back.tau[j] / fwd.tau[i] - 1) > _DELAY_RTOL:
                    errs.append(f"delay {fwd.tau[i]:.9e} vs {back.tau[j]:.9e} s")
                if abs(abs(back.a[j]) / abs(fwd.a[i]) - 1) > 1e-4:
                    errs.append(f"|a| {abs(fwd.a[i]):.6e} vs {abs(back.a[j]):.6e}")
                if fwd.pol is not None and back.pol is not None and (
                        np.abs(back.pol[j] - fwd.pol[i].T).max()
                        > 1e-4 * np.abs(fwd.pol[i]).max()):
                    errs.append("pol of the reverse LOS path is not the transpose")
                if _angle(_r_hat(fwd.theta_t[i], fwd.phi_t[i]),
                          _r_hat(back.theta_r[j], back.phi_r[j])) > _ANGLE_TOL:
                    errs.append("departure angle != reversed arrival angle")
            rep.add("reciprocity", not errs, "; ".join(errs) or f"{tx}<->{rx}")
        except ValueError as exc:
            rep.add("reciprocity", False, f"reverse link {rx}->{tx} failed: {exc}")

    again = tracer(scene, poses, links)
    errs = [f"{lk[0]}->{lk[1]}: {m}" for lk in links if (m := _same(res[lk], again[lk]))]
    rep.add("determinism", not errs, "; ".join(errs))

    if check_errors:
        name = links[0][1]
        p = poses[name]
        for what, bad in (("NaN position", (math.nan, p.position[1], p.position[2])),
                          ("position outside the scene",
                           tuple(np.asarray(scene.bounds_max) + 10.0))):
            try:
                tracer(scene, {**poses, name: replace(p, position=bad)}, links)
                rep.add(f"errors: {what}", False, "no ValueError raised")
            except ValueError as exc:
                rep.add(f"errors: {what}", repr(name) in str(exc) or name in str(exc),
                        str(exc))
    if raise_on_failure and not rep.passed:
        raise AssertionError("tracer conformance failed:\n" + str(rep))
    return rep


# --------------------------------------------------------------- exact path sets

@dataclass
class PathSetComparison:
    """One link traced by a backend against Sionna's own solver (see :func:`compare_path_sets`).

    Attributes:
        link: ``(tx, rx)``.
        position: the receiver's array centre, m.
        repeats: pairs of repeated paths in the backend's result.
        missing_db: ``[M]`` dB relative to the link's strongest reference path,
            of each reference path the backend lacks.
        extra_db: likewise for backend paths the reference lacks (and, with a
            ``confirm`` reference, that one lacks too).
        found_more_db: backend paths the reference lacks but the ``confirm``
            reference (more rays) holds: real paths the reference's rays missed.
        cfr_error: relative Frobenius error of the backend's eq.-4 channel
            against Sionna's ``Paths.cfr`` (single isotropic elements), NaN when
            the two path sets differ.
    """

    link: Link
    position: np.ndarray
    repeats: list
    missing_db: np.ndarray
    extra_db: np.ndarray
    cfr_error: float
    found_more_db: np.ndarray = field(default_factory=lambda: np.zeros(0))


class SionnaReference:
    """Sionna RT's own ``PathSolver`` and ``Paths.cfr`` on a fresh copy of a
    scene file: the independent reference for :func:`compare_path_sets`.

    Uses only Sionna's public API: ``load_scene(merge_shapes=False)``,
    ``Transmitter``/``Receiver`` with single isotropic V elements,
    ``PathSolver(deterministic=True)`` with ``synthetic_array=True``, one
    receiver per call (Sionna's per-call chain de-duplication table is then
    never shared between receivers).

    Args:
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene` (its file is reloaded; edits
            made to the live scene are not seen).
        samples_per_src: rays per source of the reference (e.g. 1e6 or 1e7).
    """

    def __init__(self, scene, samples_per_src: int):
        from ..utils import llvm

        llvm.configure_llvm()
        import sionna.rt as rt

        cfg = scene.config
        self.config = cfg
        self.samples_per_src = int(samples_per_src)
        self.sc = rt.load_scene(str(cfg.scene.file), merge_shapes=False)
        self.sc.frequency = cfg.scene.frequency_hz
        arr = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        self.sc.tx_array = self.sc.rx_array = arr
        self.solver = rt.PathSolver(deterministic=True)
        self._rt = rt

    def __call__(self, txs: list[DevicePose], rx: DevicePose, freqs_hz: np.ndarray):
        """Paths of the links ``txs[i] -> rx`` and Sionna's channels at baseband
        ``freqs_hz`` (one solver call; Sionna de-duplicates chains per source,
        so the transmitters do not share a hash table).

        Returns:
            per transmitter ``(LinkPaths, cfr [S] complex128)``.
        """
        from .base import sionna_orientation

        rt, sc, t = self._rt, self.sc, self.config.tracer
        for n in list(sc.transmitters) + list(sc.receivers):
            sc.remove(n)
        for k, tx in enumerate(txs):
            sc.add(rt.Transmitter(f"ref-tx{k}", position=tx.position,
                                  orientation=sionna_orientation(tx.orientation)))
        sc.add(rt.Receiver("ref-rx", position=rx.position,
                           orientation=sionna_orientation(rx.orientation)))
        p = self.solver(sc, max_depth=t.max_depth, max_num_paths_per_src=t.max_num_paths_per_src,
                        samples_per_src=self.samples_per_src, synthetic_array=True, los=t.los,
                        specular_reflection=t.specular_reflection,
                        diffuse_reflection=t.diffuse_reflection, refraction=t.refraction,
                        diffraction=t.diffraction, seed=t.seed)
        nt, d = len(txs), max(1, t.max_depth)
        h = np.asarray(p.cfr(frequencies=np.asarray(freqs_hz, np.float32),
                             normalize_delays=False, out_type="numpy"),
                       np.complex128).reshape(nt, -1)  # [1, 1, T, 1, 1, S]
        valid = np.asarray(p.valid.numpy(), bool).reshape(nt, -1)
        ar, ai = p.a
        a = (np.asarray(ar.numpy(), np.float64)
             + 1j * np.asarray(ai.numpy(), np.float64)).reshape(nt, -1)
        f = lambda x: np.asarray(x.numpy(), np.float64).reshape(nt, -1)  # noqa: E731
        tau, tht, pht, thr, phr = (f(x) for x in (p.tau, p.theta_t, p.phi_t, p.theta_r,
                                                  p.phi_r))
        inter = np.asarray(p.interactions.numpy()).reshape(d, nt, -1)
        vert = np.asarray(p.vertices.numpy(), np.float64).reshape(d, nt, -1, 3)
        out = []
        for k, tx in enumerate(txs):
            m = valid[k]
            order = np.argsort(tau[k][m], kind="stable")
            it = inter[:, k].T[m][order].astype(np.int32)
            vt = np.moveaxis(vert[:, k], 0, 1)[m][order]
            vt[it == 0] = 0.0
            lp = LinkPaths(tx=f"ref-tx{k}", rx="ref-rx",
                           tx_position=np.asarray(tx.position, float),
                           rx_position=np.asarray(rx.position, float),
                           tx_orientation=np.asarray(tx.orientation, float),
                           rx_orientation=np.asarray(rx.orientation, float),
                           frequency_hz=float(self.config.scene.frequency_hz),
                           a=a[k][m][order], tau=tau[k][m][order],
                           doppler=np.zeros(int(m.sum())), theta_t=tht[k][m][order],
                           phi_t=pht[k][m][order], theta_r=thr[k][m][order],
                           phi_r=phr[k][m][order], vertices=vt, interactions=it)
            out.append((lp, h[k]))
        return out


def link_cfr(lp: LinkPaths, freqs_hz: np.ndarray) -> np.ndarray:
    """The engine's eq.-4 channel of ``lp`` for single isotropic elements ``[S]``."""
    from ..phy.arrays import PlanarArray
    from ..phy.channel import baseband_gains, cfr_at

    one = PlanarArray(1, 1)
    b = baseband_gains(lp.a, lp.tau, lp.frequency_hz)
    return cfr_at(b, lp.tau, lp.theta_r, lp.phi_r, lp.theta_t, lp.phi_t, freqs_hz,
                  one, one)[:, 0, 0]


def robot_points(scene, n: int, height: float, *, clearance: float = 0.11, seed: int = 0,
                 lattice: float | None = None) -> np.ndarray:
    """``n`` random floor points where a robot fits, plus points on probe-lattice lines.

    A point qualifies when it is in free space (:func:`~isac_twin.raytrace.raw.free_points`)
    and no surface lies within ``clearance`` m of it horizontally (16 rays) at
    ``height`` and at 5 cm above the floor (a TurtleBot3 burger's footprint
    radius is 0.105 m). With ``lattice`` (the probe spacing, m), up to 4 more
    such points lie exactly on lattice lines (x, y or both a multiple of it).

    Returns:
        ``[n (+ up to 4), 3]`` m.
    """
    import mitsuba as mi

    from .raw import free_points

    lo, hi = np.asarray(scene.bounds_min, float), np.asarray(scene.bounds_max, float)
    floor = float(lo[2])
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)

    def fits(q) -> bool:
        if not free_points(scene.sionna, q[None])[0]:
            return False
        for z in (height, floor + 0.05):
            o = np.repeat([[q[0], q[1], z]], len(dirs), 0).astype(np.float32)
            ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i]) for i in range(3))),
                           mi.Vector3f(*(mi.Float(dirs[:, i].astype(np.float32))
                                         for i in range(3))))
            ray.maxt = clearance
            if np.asarray(scene.sionna.mi_scene.ray_test(ray).numpy()).any():
                return False
        return True

    pts: list[np.ndarray] = []
    tries = 0
    while len(pts) < n:
        tries += 1
        if tries > 200 * max(n, 1):
            raise ValueError(f"found only {len(pts)} of {n} points with {clearance} m "
                             "clearance in the scene")
        q = np.r_[rng.uniform(lo[:2], hi[:2]), height]
        if fits(q):
            pts.append(q)
    if lattice:
        extra = []
        for q in pts:
            snapped = [np.r_[np.round(q[0] / lattice) * lattice, q[1], height],
                       np.r_[q[0], np.round(q[1] / lattice) * lattice, height],
                       np.r_[np.round(q[:2] / lattice) * lattice, height]]
            extra += [c for c in snapped if fits(c)]
            if len(extra) >= 4:
                break
        pts += extra[:4]
    return np.asarray(pts)


def compare_path_sets(results: Iterable[Mapping[Link, LinkPaths]], reference: SionnaReference,
                      freqs_hz: np.ndarray | None = None,
                      cache: dict | None = None,
                      confirm: SionnaReference | Sequence[SionnaReference] | None = None
                      ) -> list[PathSetComparison]:
    """Each link of each backend result against Sionna's own trace of it.

    Args:
        results: backend outputs ``{(tx, rx): LinkPaths}`` (e.g. one per
            receiver position).
        reference: the :class:`SionnaReference` (its ray count decides what
            "complete" means).
        freqs_hz: baseband subcarrier offsets for the channel comparison
            (default: 64 offsets over +-40 MHz).
        cache: a dict that keeps reference (and confirmation) traces between
            calls (keyed by the two poses; the same ``freqs_hz`` must be used).
        confirm: a reference with more rays (or a sequence of them, asked in
            turn while paths remain unconfirmed), asked only about links with
            paths that ``reference`` lacks: those it holds are real paths that
            ``reference``'s rays missed (``found_more_db``), not extra.
    """
    if freqs_hz is None:
        freqs_hz = np.linspace(-40e6, 40e6, 64)
    cache = {} if cache is None else cache

    def key(pose: DevicePose) -> tuple:
        return tuple(np.round(np.r_[pose.position, pose.orientation], 9))

    out = []
    for res in results:
        pose = {}
        for lk, lp in res.items():
            pose[lk] = (DevicePose(lp.tx_position, lp.tx_orientation),
                        DevicePose(lp.rx_position, lp.rx_orientation))
        by_rx: dict[tuple, list] = {}
        for lk, (tx, rx) in pose.items():
            if (key(tx), key(rx)) not in cache:
                by_rx.setdefault(key(rx), [rx, []])[1].append(tx)
        for rx, txs in by_rx.values():
            for tx, r in zip(txs, reference(txs, rx, freqs_hz)):
                cache[(key(tx), key(rx))] = r
        for lk, lp in res.items():
            tx, rx = pose[lk]
            ref, h_ref = cache[(key(tx), key(rx))]
            top = float(np.abs(ref.a).max(initial=0.0)) or 1.0
            m = match_paths(lp, ref)
            hit = np.zeros(lp.num_paths, bool)
            hit[m[m >= 0]] = True
            db = lambda a: 20 * np.log10(np.maximum(np.abs(a), 1e-300) / top)  # noqa: E731
            missing, extra, more = db(ref.a[m < 0]), db(lp.a[~hit]), np.zeros(0)
            if extra.size and confirm is not None:
                seen = np.zeros(lp.num_paths, bool)
                for ref_more in (confirm if isinstance(confirm, (list, tuple)) else [confirm]):
                    if (hit | seen).all():
                        break
                    ck = ("confirm", ref_more.samples_per_src, key(tx), key(rx))
                    if ck not in cache:
                        cache[ck] = ref_more([tx], rx, freqs_hz)[0]
                    mb = match_paths(lp, cache[ck][0])
                    seen[mb[mb >= 0]] = True
                more, extra = db(lp.a[~hit & seen]), db(lp.a[~hit & ~seen])
            err = math.nan
            if missing.size == 0 and extra.size == 0 and more.size == 0:
                h = link_cfr(lp, freqs_hz)
                err = float(np.linalg.norm(h - h_ref) / max(np.linalg.norm(h_ref), 1e-300))
            out.append(PathSetComparison(lk, np.asarray(lp.rx_position, float),
                                         find_repeats(lp), missing, extra, err, more))
    return out


def check_path_sets(comparisons: list[PathSetComparison], *, within_db: float = 40.0,
                    cfr_rtol: float = 1e-4) -> ConformanceReport:
    """The verdicts on :func:`compare_path_sets`' output.

    * ``repeats``: no link has a repeated path;
    * ``complete``: no reference path within ``within_db`` of its link's
      strongest path is missing;
    * ``no extra``: every path the backend returns is in the reference;
    * ``cfr``: where both path sets are equal, the backend's channel is within
      ``cfr_rtol`` (relative Frobenius) of Sionna's ``Paths.cfr``.
    """
    rep = ConformanceReport()
    n = len(comparisons)

    def where(c):
        return f"{c.link[0]}->{c.link[1]} at {np.round(c.position, 3).tolist()}"

    bad = [c for c in comparisons if c.repeats]
    rep.add("repeats", not bad, f"{len(bad)} of {n} links repeat paths"
            + ("; e.g. " + where(bad[0]) + f": {len(bad[0].repeats)} pairs" if bad else ""))
    bad = [c for c in comparisons if np.any(c.missing_db >= -within_db)]
    rep.add("complete", not bad,
            f"{len(bad)} of {n} links miss paths within {within_db:g} dB"
            + ("; e.g. " + where(bad[0]) + f": {np.round(np.sort(bad[0].missing_db)[::-1], 1).tolist()[:5]} dB"
               if bad else ""))
    bad = [c for c in comparisons if c.extra_db.size]
    rep.add("no extra", not bad, f"{len(bad)} of {n} links have paths the reference lacks"
            + ("; e.g. " + where(bad[0]) + f": {np.round(bad[0].extra_db, 1).tolist()[:5]} dB"
               if bad else ""))
    more = [c for c in comparisons if c.found_more_db.size]
    if more:
        rep.add("found more", True, f"{len(more)} of {n} links hold paths the reference's rays "
                "missed and its confirmation found; e.g. " + where(more[0])
                + f": {np.round(more[0].found_more_db, 1).tolist()[:5]} dB")
    same = [c for c in comparisons if not math.isnan(c.cfr_error)]
    worst = max((c.cfr_error for c in same), default=0.0)
    rep.add("cfr", bool(same) and worst <= cfr_rtol,
            f"{len(same)} of {n} links with equal path sets; max relative error {worst:.2e}")
    return rep
