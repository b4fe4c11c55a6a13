"""The small lab the twin's tests step: a 6 x 4 x 3 m room with a metal cabinet,
AP1 (2x2) and AP2 (1x1) on disjoint symbols, robot1 (real Sionna tracing)."""

import pytest

from isac_twin.scene.synthetic import two_ap_lab


@pytest.fixture(scope="package")
def lab(tmp_path_factory):
    """The lab's scene folder (shared: a test that changes files copies it first)."""
    return two_ap_lab(tmp_path_factory.mktemp("lab") / "lab",
                      furniture={"cabinet": ((4.5, 0.2, 0), (5.1, 0.8, 1.8), "metal", 0.01)},
                      tracer={"samples_per_src": 20000, "max_depth": 2})
