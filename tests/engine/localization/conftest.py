"""A small synthetic room and its coarse fingerprint database, shared by the tests."""

import numpy as np
import pytest

from engine.synthetic import SyntheticDevice, SyntheticObject, box_mesh, write_scene_folder


def small_lab(folder, frequency_hz: float = 2.4e9):
    """A 5 x 4 x 2.5 m room with a metal cabinet and a wooden table, AP1 (2x2) and
    AP2 (1x1) on disjoint symbols, a burger robot with 2 antennas at (2.5, 2)."""
    sx, sy, sz = 5.0, 4.0, 2.5
    w = 0.1
    slabs = {
        "floor": ((0, 0, -w), (sx, sy, 0)), "ceiling": ((0, 0, sz), (sx, sy, sz + w)),
        "wall_xmin": ((-w, 0, 0), (0, sy, sz)), "wall_xmax": ((sx, 0, 0), (sx + w, sy, sz)),
        "wall_ymin": ((0, -w, 0), (sx, 0, sz)), "wall_ymax": ((0, sy, 0), (sx, sy + w, sz)),
    }
    objs = [SyntheticObject(n, *box_mesh(lo, hi)) for n, (lo, hi) in slabs.items()]
    objs.append(SyntheticObject("cabinet", *box_mesh((4.2, 0.2, 0), (4.8, 0.8, 1.8)),
                                material="metal", thickness=0.01))
    objs.append(SyntheticObject("table", *box_mesh((0.3, 3.0, 0), (1.3, 3.7, 0.75)),
                                material="wood", thickness=0.03))
    devs = [SyntheticDevice("AP1", "access_point", "tx", (0.1, 2.0, 2.0), rows=2, cols=2,
                            extra={"symbols": [0, 7]}),
            SyntheticDevice("AP2", "access_point", "tx", (2.5, 0.1, 2.0),
                            orientation=(0.0, 0.0, 1.5708), extra={"symbols": [7, 14]}),
            SyntheticDevice("robot1", "robot", "rx", (3.3, 2.0, 0.0), cols=2,
                            orientation=(0.0, 0.0, 1.5708),
                            extra={"model": "burger", "antenna_offset": [0.0, 0.0, 0.25]})]
    return write_scene_folder(folder, objs, devs, [("AP1", "robot1"), ("AP2", "robot1")],
                              frequency_hz=frequency_hz,
                              tracer={"samples_per_src": 10000, "max_depth": 2})


@pytest.fixture(scope="session")
def lab(tmp_path_factory):
    return small_lab(tmp_path_factory.mktemp("loc") / "lab")


@pytest.fixture(scope="session")
def lab_db(lab, tmp_path_factory):
    """A 0.4 m database of the small lab (cached in a temp folder)."""
    from engine.localization.fingerprints import cached_database
    from engine.scene import load_scene

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
