"""A small synthetic room and its coarse fingerprint database, shared by the tests."""

import numpy as np
import pytest

from isac_twin.scene.synthetic import two_ap_lab


def small_lab(folder, frequency_hz: float = 2.4e9):
    """A 5 x 4 x 2.5 m room with a metal cabinet and a wooden table, AP1 (2x2) and
    AP2 (1x1) on disjoint symbols, a burger robot with 2 antennas at (3.3, 2)."""
    furniture = {"cabinet": ((4.2, 0.2, 0), (4.8, 0.8, 1.8), "metal", 0.01),
                 "table": ((0.3, 3.0, 0), (1.3, 3.7, 0.75), "wood", 0.03)}
    return two_ap_lab(folder, size=(5.0, 4.0, 2.5), furniture=furniture, ap2=(2.5, 0.1, 2.0),
                      robot=(3.3, 2.0, 0.0), frequency_hz=frequency_hz,
                      tracer={"samples_per_src": 10000, "max_depth": 2})


@pytest.fixture(scope="session")
def lab(tmp_path_factory):
    return small_lab(tmp_path_factory.mktemp("loc") / "lab")


@pytest.fixture(scope="session")
def lab_db(lab, tmp_path_factory):
    """A 0.4 m database of the small lab (cached in a temp folder)."""
    from isac_twin import load_scene
    from isac_twin.localization.fingerprints import cached_database

    cache = tmp_path_factory.mktemp("cache")
    return cached_database(load_scene(lab), spacing=0.4, cache_dir=cache, max_paths=16,
                           verify=0)


@pytest.fixture(scope="session")
def make_lab():
    """``make_lab(folder, frequency_hz=...)`` -> a small-lab scene folder."""
    return small_lab


@pytest.fixture
def rng():
    return np.random.default_rng(0)
