"""The front-end drift study's rotation error rate and jitter (bench/study_front_end_drift.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.geometry import se3, so3_exp


@pytest.fixture
def study(bench):
    return bench("study_front_end_drift")


def walk(stamps_s: np.ndarray, turn_deg_per_s: float = 3.0) -> np.ndarray:
    """A true walk along x at 1.2 m/s, turning about z."""
    return np.stack([se3(so3_exp(np.radians([0.0, 0.0, turn_deg_per_s * t])),
                         np.array([1.2 * t, 0, 0])) for t in stamps_s])


def test_a_steady_pitch_error_is_its_rate_and_no_jitter(study):
    stamps_s = 0.1 * np.arange(400)
    T_true = walk(stamps_s, turn_deg_per_s=0.0)  # (turning, the axes mix within a window)
    # the estimate turns about its own y axis 0.06 deg/s more than the truth
    T_est = np.stack([T @ se3(so3_exp(np.radians([0.0, 0.06 * t, 0.0])), np.zeros(3))
                      for T, t in zip(T_true, stamps_s, strict=True)])
    drift = study.rotation_drift(stamps_s, T_est, T_true, window_s=5.0)
    np.testing.assert_allclose(drift["rate_deg_per_s"], [0.0, 0.06, 0.0], atol=1e-4)
    np.testing.assert_allclose(drift["jitter_deg"], [0.0, 0.0, 0.0], atol=1e-3)


def test_pose_noise_is_jitter_not_drift(study):
    rng = np.random.default_rng(3)
    stamps_s = 0.1 * np.arange(4000)
    T_true = walk(stamps_s)
    sigma_deg = np.array([0.2, 0.5, 0.1])
    T_est = np.stack([T @ se3(so3_exp(np.radians(rng.normal(0, sigma_deg))), np.zeros(3))
                      for T in T_true])
    drift = study.rotation_drift(stamps_s, T_est, T_true, window_s=5.0)
    # one scan's relative error holds two independent pose errors
    np.testing.assert_allclose(drift["jitter_deg"], np.sqrt(2) * sigma_deg, rtol=0.06)
    assert np.all(np.abs(drift["rate_deg_per_s"]) < 0.02)


def test_a_log_shorter_than_a_window_is_refused(study):
    stamps_s = 0.1 * np.arange(10)
    with pytest.raises(ValueError, match="shorter than one"):
        study.rotation_drift(stamps_s, walk(stamps_s), walk(stamps_s), window_s=5.0)
