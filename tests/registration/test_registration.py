"""Pairwise registration API (preprocess + align) on real Velodyne HDL-32E data.

Data: ../shared/data/hdl32_pair (koide3/fast_gicp, BSD-3-Clause; T_target_source.txt from
koide3/small_gicp, MIT): two consecutive outdoor scans and their GICP relative pose.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import PointCloudError
from mcl3d.core.geometry import rotation_angle, se3, se3_inverse, so3_exp


@pytest.fixture(scope="module")
def hdl32(shared_data):
    from mcl3d.io.logs.cloud_files import read_cloud_file
    from mcl3d.registration.align import preprocess

    folder = shared_data / "hdl32_pair"
    target = read_cloud_file(folder / "251370668.pcd").points
    source = read_cloud_file(folder / "251371071.pcd").points
    reference = np.loadtxt(folder / "T_target_source.txt")
    return preprocess(target, 0.1), preprocess(source, 0.1), reference


def test_hdl32_pair_matches_the_reference_pose(ti_runtime, hdl32):
    from mcl3d.registration.align import align

    target, source, reference = hdl32
    result = align(target, source)
    error = se3_inverse(reference) @ result.T_target_source
    assert result.converged
    assert np.linalg.norm(error[:3, 3]) < 0.02
    assert np.degrees(rotation_angle(error[:3, :3])) < 0.2
    assert result.num_inliers > 0.5 * len(source)
    assert np.linalg.eigvalsh(result.H).min() > 0  # well constrained: a usable covariance
    assert "converged=True" in repr(result)


@pytest.mark.parametrize("use_lm", [False, True])
def test_hdl32_pair_from_a_perturbed_guess(ti_runtime, hdl32, use_lm):
    """Back from 3° and 37 cm off, with Gauss-Newton and with Levenberg-Marquardt."""
    from mcl3d.registration.align import align

    target, source, reference = hdl32
    guess = reference @ se3(so3_exp(np.radians([1.0, -1.0, 3.0])), [0.3, -0.2, 0.1])
    result = align(target, source, guess, use_lm=use_lm)
    error = se3_inverse(reference) @ result.T_target_source
    assert result.converged
    assert np.linalg.norm(error[:3, 3]) < 0.02
    assert np.degrees(rotation_angle(error[:3, :3])) < 0.2


def test_empty_clouds_are_rejected(ti_runtime):
    from mcl3d.registration.align import Scan, align

    empty = Scan(np.zeros((0, 3)), np.zeros((0, 3, 3)))
    full = Scan(np.ones((10, 3)), np.tile(np.eye(3), (10, 1, 1)))
    with pytest.raises(PointCloudError, match="source point cloud is empty"):
        align(full, empty)
