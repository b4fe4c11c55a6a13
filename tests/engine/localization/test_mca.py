"""engine/localization/mca.py: exactness of the branch-and-bound query against brute force."""

import numpy as np
import pytest

from engine.localization.mca import MCALocalizer


def _room_db(rng, nx=40, ny=30, aps=((0.1, 3.0, 2.0), (7.9, 1.0, 2.0)), L=12):
    """Synthetic fingerprints: LOS length plus image-source-like extra lengths."""
    xs, ys = np.meshgrid(np.linspace(0.5, 7.5, nx), np.linspace(0.5, 5.5, ny), indexing="ij")
    pos = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.25)], axis=1)
    lengths = np.full((len(pos), len(aps), L), np.nan)
    for a, ap in enumerate(aps):
        ap = np.array(ap)
        # Images of the AP in the 4 walls and floor/ceiling of an 8 x 6 x 3 room.
        images = [ap, ap * [-1, 1, 1], [16 - ap[0], ap[1], ap[2]], ap * [1, -1, 1],
                  [ap[0], 12 - ap[1], ap[2]], ap * [1, 1, -1], [ap[0], ap[1], 6 - ap[2]]]
        d = np.stack([np.linalg.norm(pos - np.array(im), axis=1) for im in images], axis=1)
        lengths[:, a, :d.shape[1]] = d
    return pos, lengths


def test_query_equals_brute_force_top_k():
    rng = np.random.default_rng(1)
    pos, lengths = _room_db(rng)
    loc = MCALocalizer(pos, lengths, eps=0.5, k=4)
    all_idx = np.arange(len(pos))
    for trial in range(20):
        truth = rng.integers(len(pos))
        meas = lengths[truth] + rng.normal(0, 0.05, lengths[truth].shape)
        meas[:, rng.integers(0, 7)] = np.nan  # a missed path
        est = loc(meas)
        brute = loc.exact_scores(loc._check_measured(meas), all_idx)
        top = np.sort(brute)[::-1][:4]
        np.testing.assert_allclose(est.best_scores, top, rtol=1e-9)
        # The bound prunes: far fewer exact scores than points.
        assert est.candidates_scored < len(pos)


def test_noise_free_query_finds_the_point():
    pos, lengths = _room_db(np.random.default_rng(0))
    loc = MCALocalizer(pos, lengths, k=1)
    for i in (0, 17, 555, len(pos) - 1):
        est = loc(lengths[i])
        assert est.best_indices[0] == i
        np.testing.assert_allclose(est.position, pos[i])


def test_score_formula_by_hand():
    pos = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    lengths = np.array([[[2.0, 5.0]], [[2.3, np.nan]]])
    loc = MCALocalizer(pos, lengths, eps=0.5, k=1)
    meas = np.array([[2.1, 4.0]])
    s = loc.exact_scores(meas, np.array([0, 1]))
    # point 0: |2.1-2.0| = 0.1 -> 0.16; |4.0-5.0| = 1.0 >= eps -> 0.
    # point 1: |2.1-2.3| = 0.2 -> 0.09; |4.0-2.3| = 1.7 -> 0.
    np.testing.assert_allclose(s, [0.16, 0.09])
    assert loc(meas).best_indices[0] == 0


@pytest.mark.parametrize("bad,match", [
    (np.array([[1.0, 2.0]]), r"expected \[A=2, J\]"),
    (np.array([[1.0, np.inf], [1.0, 2.0]]), "finite and >= 0"),
    (np.array([[-1.0, 2.0], [1.0, 2.0]]), "finite and >= 0"),
])
def test_bad_measurement(bad, match):
    pos, lengths = _room_db(np.random.default_rng(0), nx=4, ny=3)
    with pytest.raises(ValueError, match=match):
        MCALocalizer(pos, lengths)(bad)


def test_bad_database():
    with pytest.raises(ValueError, match=r"lengths: expected shape \[P=2"):
        MCALocalizer(np.zeros((2, 3)), np.zeros((3, 1, 2)))
    with pytest.raises(ValueError, match="k: expected 1..2"):
        MCALocalizer(np.zeros((2, 3)), np.zeros((2, 1, 2)), k=5)
