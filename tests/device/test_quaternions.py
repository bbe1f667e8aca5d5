"""The kinematics' quaternion conversions (twin/device/kinematics.py) against scipy's Rotation, on drawn
rotations and on the half turns where the branch (and so the sign) changes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twin.device.kinematics import matrix_quat, quat_matrix

DRAWN = Rotation.random(2000, random_state=20261127)
HALF_TURNS = Rotation.from_rotvec(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, -1]])
                                  / np.linalg.norm([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, -1]], axis=1,
                                                   keepdims=True))


@pytest.mark.parametrize("rotations", [DRAWN, HALF_TURNS, Rotation.identity(1)], ids=["drawn", "half turns", "none"])
def test_matrix_to_quaternion_is_scipys_sign_and_all(rotations):
    for matrix in rotations.as_matrix():
        assert np.allclose(matrix_quat(matrix), Rotation.from_matrix(matrix).as_quat(scalar_first=True),
                           rtol=0, atol=1e-12)


def test_quaternion_to_matrix_is_scipys():
    for quat in DRAWN.as_quat(scalar_first=True):
        assert np.allclose(quat_matrix(quat), Rotation.from_quat(quat, scalar_first=True).as_matrix(), rtol=0,
                           atol=1e-12)
    for matrix in DRAWN.as_matrix()[:50]:  # and back
        assert np.allclose(quat_matrix(matrix_quat(matrix)), matrix, rtol=0, atol=1e-12)
