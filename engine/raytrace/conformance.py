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
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from engine.raytrace.base import (INTERACTION_DIFFRACTION, INTERACTION_DIFFUSE,
                                  INTERACTION_NONE, INTERACTION_REFRACTION,
                                  INTERACTION_SPECULAR, SPEED_OF_LIGHT, DevicePose, Link,
                                  LinkPaths, device_poses, resolve_links)

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
        tracer: a :class:`~engine.raytrace.base.Tracer`.
        scene: the :class:`~engine.scene.TwinScene`; at least one link should be
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
