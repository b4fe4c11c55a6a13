"""isac_twin.raytrace.polarization: the element's V vector in world components."""

from __future__ import annotations

import numpy as np
import pytest

import isac_twin.raytrace.polarization as pol
from isac_twin.phy.arrays import r_hat
from isac_twin.utils.geometry import rotation_matrix


@pytest.mark.parametrize("gather", [0, 10 ** 9])
def test_v_world_equals_per_path_rotation(monkeypatch, gather):
    """Gathered per path (few paths) or once per distinct orientation (many):
    the values of ``local_to_world`` with each path's rotation, bit for bit,
    and exactly (1, 0) for an orientation of zero."""
    rng = np.random.default_rng(1)
    n = 3000
    k = r_hat(rng.uniform(0, np.pi, n), rng.uniform(-np.pi, np.pi, n))
    ori = np.array([[0.3, -0.2, 0.1], [1.2, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.2],
                    [1.2, 0.0, 0.0]])
    idx = rng.integers(0, len(ori), n)
    mats = np.stack([rotation_matrix(o[2], o[1], o[0]) for o in ori])  # Sionna [yaw, pitch, roll]
    ref = pol.local_to_world(k, mats[idx])[2][:, :, 0]
    monkeypatch.setattr(pol, "V_WORLD_GATHER", gather)
    got = pol.v_world(k, ori, idx)
    zero = idx == 2
    np.testing.assert_array_equal(got[~zero], ref[~zero])
    np.testing.assert_array_equal(got[zero], np.tile([1.0, 0.0], (zero.sum(), 1)))
    np.testing.assert_allclose(ref[zero], got[zero], atol=1e-15)  # the world frame
    # a V element seen broadside from any direction: unit norm in the sphere's basis
    np.testing.assert_allclose(np.linalg.norm(got, axis=1)[~zero] <= 1 + 1e-12, True)
