"""engine/localization/mca.py: exactness of the branch-and-bound query against brute force."""

import numpy as np
import pytest

from isac_twin.localization.mca import MCALocalizer


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


# ---------------------------------------------------------------- with directions (issue 13)


def _mirror_db():
    """One AP on the room's symmetry line y = 3: points mirrored about it have the
    same path lengths; directions (unit vectors from each image to the point)
    differ."""
    pos, lengths = _room_db(None, aps=((0.1, 3.0, 2.0),), L=7)
    ap = np.array([0.1, 3.0, 2.0])
    images = np.array([ap, ap * [-1, 1, 1], [16 - ap[0], ap[1], ap[2]], ap * [1, -1, 1],
                       [ap[0], 12 - ap[1], ap[2]], ap * [1, 1, -1], [ap[0], ap[1], 6 - ap[2]]])
    v = pos[:, None, :] - images[None]  # [P, 7, 3]
    dirs = (v / np.linalg.norm(v, axis=2, keepdims=True))[:, None]  # [P, 1, 7, 3]
    return pos, lengths, dirs


def test_directions_break_ties_that_lengths_cannot():
    pos, lengths, dirs = _mirror_db()
    # a point and its mirror image about y = 3 have equal lengths (grid i = ix * 30 + iy)
    i, mirror = 10 * 30 + 20, 10 * 30 + 9
    np.testing.assert_allclose(pos[mirror, 1], 6.0 - pos[i, 1])
    np.testing.assert_allclose(np.sort(lengths[mirror]), np.sort(lengths[i]), atol=1e-9)
    by_length = MCALocalizer(pos, lengths, eps=0.5, k=2)(lengths[i])
    assert set(by_length.best_indices) == {i, mirror}  # a tie: half-way between them
    assert by_length.best_scores[0] == pytest.approx(by_length.best_scores[1])
    loc = MCALocalizer(pos, lengths, eps=0.5, k=1, directions=dirs, angle_weight_m=3.0)
    assert loc(lengths[i], dirs[i]).best_indices[0] == i
    assert loc(lengths[mirror], dirs[mirror]).best_indices[0] == mirror
    # without measured directions the localizer is the length-only one
    assert loc(lengths[i]).best_scores[0] == pytest.approx(by_length.best_scores[0])


def test_query_with_directions_and_weights_equals_brute_force():
    """The length-only bound table stays an upper bound with directions and
    weights: the branch and bound returns the exact top k."""
    rng = np.random.default_rng(4)
    pos, lengths, dirs = _mirror_db()
    loc = MCALocalizer(pos, lengths, eps=0.5, k=4, directions=dirs, angle_weight_m=2.0)
    all_idx = np.arange(len(pos))
    for _ in range(10):
        t = rng.integers(len(pos))
        meas = lengths[t] + rng.normal(0, 0.05, lengths[t].shape)
        k = dirs[t] + rng.normal(0, 0.02, dirs[t].shape)
        k[0, 3] = np.nan  # a path without a direction
        w = rng.uniform(0, 1, meas.shape)
        est = loc(meas, k, w)
        brute = loc.exact_scores(meas, all_idx, k, w)
        np.testing.assert_allclose(est.best_scores, np.sort(brute)[::-1][:4], rtol=1e-9)


def test_direction_inputs_are_checked():
    pos, lengths, dirs = _mirror_db()
    with pytest.raises(ValueError, match=r"directions: expected shape \[1200, 1, 7, 3\]"):
        MCALocalizer(pos, lengths, directions=dirs[:, :, :3])
    with pytest.raises(ValueError, match="angle_weight_m"):
        MCALocalizer(pos, lengths, directions=dirs, angle_weight_m=0.0)
    loc = MCALocalizer(pos, lengths, directions=dirs)
    with pytest.raises(ValueError, match=r"directions: expected shape \[1, 7, 3\]"):
        loc(lengths[0], dirs[0, :, :2])
    with pytest.raises(ValueError, match="weights"):
        loc(lengths[0], dirs[0], np.full((1, 7), 2.0))


def test_directions_tighten_the_bound():
    """Scoring the heaviest directional paths exactly for the bound (the
    length-only table cannot see a direction mismatch) prunes far more points
    and returns the same exact top k as the length-only bound."""
    rng = np.random.default_rng(7)
    pos, lengths, dirs = _mirror_db()
    tight = MCALocalizer(pos, lengths, eps=0.5, k=4, directions=dirs, angle_weight_m=3.0)
    loose = MCALocalizer(pos, lengths, eps=0.5, k=4, directions=dirs, angle_weight_m=3.0,
                         exact_paths=0)
    n_tight = n_loose = 0
    for _ in range(10):
        t = rng.integers(len(pos))
        meas = lengths[t] + rng.normal(0, 0.05, lengths[t].shape)
        k = dirs[t] + rng.normal(0, 0.02, dirs[t].shape)
        k /= np.linalg.norm(k, axis=-1, keepdims=True)
        w = np.clip(rng.uniform(0, 1, meas.shape), 0, 1)
        w[0, 0] = 1.0
        a, b = tight(meas, k, w), loose(meas, k, w)
        np.testing.assert_allclose(a.best_scores, b.best_scores, rtol=1e-9)
        n_tight += a.candidates_scored
        n_loose += b.candidates_scored
    assert n_tight < n_loose / 2
    with pytest.raises(ValueError, match="exact_paths"):
        MCALocalizer(pos, lengths, directions=dirs, exact_paths=-1)
