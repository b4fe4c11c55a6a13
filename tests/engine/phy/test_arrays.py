"""Tests for isac_twin.phy.arrays: Sionna's PlanarArray geometry and steering."""

import numpy as np
import pytest

from isac_twin.phy.arrays import PlanarArray, r_hat, sionna_rotation


def test_element_order_and_positions_match_sionna_planar_array():
    # Reference values printed by sionna.rt.PlanarArray(num_rows=2, num_cols=3,
    # vertical_spacing=0.5, horizontal_spacing=0.7).normalized_positions
    ref = np.array([[0, -0.7, 0.25], [0, -0.7, -0.25], [0, 0.0, 0.25],
                    [0, 0.0, -0.25], [0, 0.7, 0.25], [0, 0.7, -0.25]])
    arr = PlanarArray(2, 3, vertical_spacing=0.5, horizontal_spacing=0.7)
    np.testing.assert_allclose(arr.normalized_positions, ref, atol=1e-12)
    assert arr.num_ant == 6


def test_sionna_rotation_is_sionnas_rotation_matrix():
    """Sionna-order ``[yaw, pitch, roll]`` -> the matrix Sionna RT's own
    ``rotation_matrix(angles)`` computes (float32), and bad input is refused by name."""
    import mitsuba as mi
    from sionna.rt.utils.geometry import rotation_matrix as sionna_rotation_matrix

    for o in ([0.3, -0.7, 1.1], [-2.9, 1.2, -0.4], [np.pi, 0.0, np.pi / 2]):
        ref = np.array(sionna_rotation_matrix(mi.Point3f(*o)), dtype=np.float64).reshape(3, 3)
        np.testing.assert_allclose(sionna_rotation(o), ref, atol=2e-6)
    with pytest.raises(ValueError, match="orientation contains NaN"):
        sionna_rotation([0.0, np.nan, 0.0])


def test_broadside_steering_is_all_ones():
    arr = PlanarArray(4, 8)
    a = arr.steering_vectors([np.pi / 2], [0.0])  # +x = boresight
    assert a.shape == (1, 32)
    np.testing.assert_allclose(a, np.ones((1, 32)), atol=1e-12)


def test_endfire_steering_has_spacing_phase_progression():
    d = 0.5
    arr = PlanarArray(1, 8, horizontal_spacing=d)
    a = arr.steering_vectors([np.pi / 2], [np.pi / 2])[0]  # along +y
    ratios = a[1:] / a[:-1]
    np.testing.assert_allclose(ratios, np.exp(2j * np.pi * d), atol=1e-12)
    # Vertical endfire (zenith): phase decreases going down the rows.
    col = PlanarArray(4, 1, vertical_spacing=0.25).steering_vectors([0.0], [0.0])[0]
    np.testing.assert_allclose(col[1:] / col[:-1], np.exp(-2j * np.pi * 0.25), atol=1e-12)


def test_orientation_rotates_the_array_with_its_boresight():
    arr = PlanarArray(2, 4)
    yaw = np.pi / 2  # boresight now +y
    a = arr.steering_vectors([np.pi / 2], [np.pi / 2], orientation=[yaw, 0, 0])
    np.testing.assert_allclose(a, 1.0, atol=1e-12)
    # Same local direction -> same steering vector, whatever the pose.
    o = np.array([0.4, -0.2, 0.9])
    k_local = r_hat(1.0, 0.3)
    k_world = sionna_rotation(o) @ k_local
    a_rot = arr.steering_vectors_from_directions(k_world[None], orientation=o)
    a_loc = arr.steering_vectors_from_directions(k_local[None])
    np.testing.assert_allclose(a_rot, a_loc, atol=1e-12)


def test_steering_batch_shape_and_unit_modulus():
    arr = PlanarArray(4, 8)
    rng = np.random.default_rng(0)
    a = arr.steering_vectors(rng.uniform(0, np.pi, 60), rng.uniform(-np.pi, np.pi, 60))
    assert a.shape == (60, 32)
    np.testing.assert_allclose(np.abs(a), 1.0)


def test_element_pattern_hook_scales_steering():
    def half(theta, phi):
        return 0.5 * np.ones_like(theta)
    a = PlanarArray(1, 2, pattern=half).steering_vectors([np.pi / 2], [0.0])
    np.testing.assert_allclose(a, 0.5)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="num_rows"):
        PlanarArray(0, 2)
    with pytest.raises(ValueError, match="pattern"):
        PlanarArray(1, 2, pattern="tr38901")
    arr = PlanarArray(1, 2)
    with pytest.raises(ValueError, match="phi"):
        arr.steering_vectors([0.1, 0.2], [0.1])
    with pytest.raises(ValueError, match="theta.*NaN"):
        arr.steering_vectors([np.nan], [0.1])
    with pytest.raises(ValueError, match="orientation"):
        arr.steering_vectors([0.1], [0.1], orientation=[0, 0])
