"""Tests for isac_twin.phy.ofdm: numerology, Sionna's frequency grid, allocations."""

import numpy as np
import pytest

from isac_twin.phy.ofdm import ResourceGrid, ResourceSet, allocation_masks

PAPER = dict(num_subcarriers=1024, subcarrier_spacing_hz=78125.0,
             num_symbols=14, cyclic_prefix_samples=72)


def test_numerology_of_the_paper_setup():
    g = ResourceGrid(**PAPER)
    assert g.bandwidth_hz == pytest.approx(80e6)
    assert g.symbol_duration_s == pytest.approx((1024 + 72) / 80e6)
    assert g.step_duration_s == pytest.approx(14 * (1024 + 72) / 80e6)
    assert g.shape == (14, 1024)
    np.testing.assert_allclose(g.symbol_times, np.arange(14) * g.symbol_duration_s)


@pytest.mark.parametrize("n", [1024, 7, 8, 1])
def test_subcarrier_frequencies_match_sionna_convention(n):
    # sionna.rt.utils.subcarrier_frequencies: [-N/2 .. N/2-1] (even),
    # [-(N-1)/2 .. (N-1)/2] (odd), times delta_f.
    g = ResourceGrid(n, 15e3, 1)
    if n % 2 == 0:
        ref = np.arange(-n // 2, n // 2) * 15e3
    else:
        ref = np.arange(-(n - 1) // 2, (n - 1) // 2 + 1) * 15e3
    np.testing.assert_array_equal(g.subcarrier_frequencies, ref)
    assert g.subcarrier_frequencies[n // 2] == 0.0


@pytest.mark.parametrize("kwargs, word", [
    (dict(num_subcarriers=0), "num_subcarriers"),
    (dict(subcarrier_spacing_hz=-1.0), "subcarrier_spacing_hz"),
    (dict(subcarrier_spacing_hz=float("nan")), "subcarrier_spacing_hz"),
    (dict(num_symbols=2.5), "num_symbols"),
    (dict(cyclic_prefix_samples=-3), "cyclic_prefix_samples"),
])
def test_grid_rejects_bad_numerology(kwargs, word):
    with pytest.raises(ValueError, match=word):
        ResourceGrid(**{**PAPER, **kwargs})


def test_resource_set_from_half_open_ranges():
    g = ResourceGrid(**PAPER)
    rs = ResourceSet(g, subcarriers=(100, 200), symbols=(2, 5), name="AP1")
    m = rs.mask
    assert m.shape == (14, 1024) and m.dtype == bool
    assert m.sum() == 100 * 3 == rs.num_resource_elements
    assert m[2, 100] and m[4, 199] and not m[5, 100] and not m[2, 200] and not m[1, 150]


def test_resource_set_defaults_to_full_grid_and_accepts_index_sets():
    g = ResourceGrid(16, 1e3, 4)
    assert ResourceSet(g).mask.all()
    rs = ResourceSet(g, subcarriers=[5, 1, 3, 3], symbols=range(0, 4, 2))
    np.testing.assert_array_equal(rs.subcarrier_indices, [1, 3, 5])
    np.testing.assert_array_equal(np.nonzero(rs.mask.any(axis=1))[0], [0, 2])


@pytest.mark.parametrize("sc, sy, match", [
    ((0, 1025), None, r"'AP2'.*subcarrier range \[0, 1025\)"),
    ((10, 10), None, r"'AP2'.*subcarrier range \[10, 10\)"),
    ((-1, 5), None, r"'AP2'.*subcarrier range"),
    (None, (0, 15), r"'AP2'.*symbol range \[0, 15\)"),
    ([3, 2000], None, r"'AP2'.*subcarrier indices \[2000\]"),
    ([], None, r"'AP2'.*non-empty"),
    ([1.5], None, r"'AP2'.*integers"),
])
def test_allocation_outside_grid_names_transmitter_and_range(sc, sy, match):
    g = ResourceGrid(**PAPER)
    with pytest.raises(ValueError, match=match):
        ResourceSet(g, subcarriers=sc, symbols=sy, name="AP2")


def test_overlap_and_stacked_masks():
    g = ResourceGrid(64, 1e3, 2)
    a = ResourceSet(g, (0, 40), name="a")
    b = ResourceSet(g, (30, 64), name="b")
    assert a.overlaps(b).sum() == 10 * 2
    masks = allocation_masks({"a": a, "b": b})
    assert masks.shape == (2, 2, 64)
    other = ResourceSet(ResourceGrid(32, 1e3, 2), name="c")
    with pytest.raises(ValueError, match="'c'"):
        allocation_masks([a, other])
