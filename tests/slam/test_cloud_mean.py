"""The SLAM cloud's mean and covariance from device moments (mcl3d.slam.cloud_mean) against
the host's weighted_pose_mean on the same poses."""

import numpy as np
import pytest

from mcl3d.core import geometry
from mcl3d.evaluation.consistency import weighted_pose_mean


def cloud(rng, n, centre_t, spread):
    """n poses about a pose at `centre_t` (m), tangent noise of `spread` (rad, m, 6)."""
    T_centre = geometry.se3(geometry.rpy_to_rot(0.2, -0.1, 2.5), centre_t)
    return T_centre @ geometry.se3_exp(rng.normal(0.0, spread, (n, 6)))


def on_device(poses, weights):
    import taichi as ti

    from mcl3d.slam.cloud_mean import CloudMean

    n = len(poses)
    q_cur = ti.Vector.field(4, ti.f32, n)
    t_cur = ti.Vector.field(3, ti.f32, n)
    q_cur.from_numpy(geometry.rot_to_quat(poses[:, :3, :3]).astype(np.float32))
    t_cur.from_numpy(poses[:, :3, 3].astype(np.float32))
    f32 = geometry.se3(geometry.quat_to_rot(q_cur.to_numpy().astype(np.float64)),
                       t_cur.to_numpy().astype(np.float64))  # the poses the device holds
    heaviest = int(np.argmax(weights))
    start = geometry.se3(f32[heaviest, :3, :3], weights @ f32[:, :3, 3])
    return CloudMean(n + 100)(q_cur, t_cur, weights, start), f32


@pytest.mark.parametrize("spread", [[0.002, 0.002, 0.01, 0.05, 0.05, 0.02],
                                    [0.05, 0.05, 0.3, 1.0, 1.0, 0.3]])
def test_mean_and_covariance_match_the_host(ti_runtime, spread):
    rng = np.random.default_rng(3)
    poses = cloud(rng, 3000, np.array([412.0, -87.0, 31.0]), spread)
    weights = rng.random(len(poses)) ** 3
    weights /= weights.sum()
    (T_mean, cov), f32_poses = on_device(poses, weights)
    T_host, cov_host = weighted_pose_mean(f32_poses, weights)
    d = geometry.se3_log(geometry.se3_inverse(T_host) @ T_mean)
    assert np.abs(d[:3]).max() < 2e-6 and np.abs(d[3:]).max() < 1e-4  # f32 of 400 m
    sd = np.sqrt(np.diag(cov_host))
    assert np.abs(cov - cov_host).max() / np.outer(sd, sd).max() < 1e-3
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0


def test_one_particle_carries_all_the_weight(ti_runtime):
    rng = np.random.default_rng(4)
    poses = cloud(rng, 600, np.array([3.0, 1.0, 0.5]), [0.1] * 6)
    weights = np.zeros(len(poses))
    weights[17] = 1.0
    (T_mean, cov), f32_poses = on_device(poses, weights)
    assert np.allclose(T_mean, f32_poses[17], atol=1e-5)
    assert np.abs(cov).max() < 1e-10
