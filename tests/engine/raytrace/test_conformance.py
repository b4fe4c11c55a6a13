"""engine/raytrace/conformance.py: the checker catches broken backends."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from engine.raytrace.conformance import check_shapes, check_tracer
from engine.raytrace.sionna import SionnaTracer


class _Broken:
    """Wraps a good tracer and breaks one thing."""

    def __init__(self, inner, how):
        self.inner, self.how = inner, how

    def __call__(self, scene, poses, links=None):
        out = self.inner(scene, poses, links)
        if self.how == "ns":
            return {k: replace(v, tau=v.tau * 1e9) for k, v in out.items()}
        if self.how == "angles":
            return {k: replace(v, phi_t=v.phi_t + np.pi / 4) for k, v in out.items()}
        if self.how == "noisy":
            rng = np.random.default_rng()
            return {k: replace(v, a=v.a * (1 + 1e-3 * rng.standard_normal(v.a.shape)))
                    for k, v in out.items()}
        return out


@pytest.fixture(scope="module")
def good(room_scene):
    return SionnaTracer(room_scene.config.tracer)


@pytest.mark.parametrize("how, failing", [("ns", "shapes+units"), ("angles", "los"),
                                          ("noisy", "determinism")])
def test_checker_catches(good, room_scene, how, failing):
    rep = check_tracer(_Broken(good, how), room_scene, check_errors=False)
    assert failing in {r.name for r in rep.failures}, str(rep)
    with pytest.raises(AssertionError, match="conformance failed"):
        check_tracer(_Broken(good, how), room_scene, check_errors=False,
                     raise_on_failure=True)


def test_check_shapes_flags_bad_arrays(good, room_scene):
    from engine.raytrace.base import device_poses

    lp = good(room_scene, device_poses(room_scene.config))[("AP1", "robot1")]
    assert check_shapes(lp) == []
    assert any("shape" in e for e in check_shapes(replace(lp, doppler=lp.doppler[:-1])))
    assert any("sorted" in e for e in check_shapes(replace(lp, tau=lp.tau[::-1])))
    assert any("theta_t" in e for e in check_shapes(replace(lp, theta_t=lp.theta_t + 4)))
