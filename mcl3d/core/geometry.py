"""SO(3)/SE(3) helpers on numpy arrays: the one place that owns pose conventions.

Poses are 4x4 float64 arrays named by frames (`T_map_lidar` maps lidar points into the map).
Quaternions are (x, y, z, w), Hamilton, as in ROS and TUM files. Tangent vectors are
rotation first (wx, wy, wz, vx, vy, vz) with right perturbation `T @ se3_exp(xi)`, as gtsam
and the Monte Carlo SLAM paper use. Functions accept batches (leading dimensions).
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-9


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix [w]x such that hat(w) @ v == cross(w, v)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def quat_to_rot(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices from (x, y, z, w) quaternions; the quaternion is normalized first."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty((*q.shape[:-1], 3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternions with w >= 0 from rotation matrices (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    q = np.empty((m.shape[0], 4))
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    use_w = trace > diag.max(axis=1)
    k = np.where(use_w, 3, diag.argmax(axis=1))
    for case in range(4):
        sel = k == case
        if not sel.any():
            continue
        s = m[sel]
        if case == 3:
            r = np.sqrt(1.0 + s[:, 0, 0] + s[:, 1, 1] + s[:, 2, 2]) * 2
            q[sel] = np.stack([(s[:, 2, 1] - s[:, 1, 2]) / r, (s[:, 0, 2] - s[:, 2, 0]) / r,
                               (s[:, 1, 0] - s[:, 0, 1]) / r, r / 4], axis=1)
        else:
            i, j, k3 = case, (case + 1) % 3, (case + 2) % 3
            r = np.sqrt(1.0 + s[:, i, i] - s[:, j, j] - s[:, k3, k3]) * 2
            qq = np.empty((s.shape[0], 4))
            qq[:, i] = r / 4
            qq[:, j] = (s[:, j, i] + s[:, i, j]) / r
            qq[:, k3] = (s[:, k3, i] + s[:, i, k3]) / r
            qq[:, 3] = (s[:, k3, j] - s[:, j, k3]) / r
            q[sel] = qq
    q = np.where(q[:, 3:4] < 0, -q, q)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(*batch, 4)


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose(s) from rotation(s) and translation(s)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_from_tq(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    return se3(quat_to_rot(q_xyzw), t_xyz)


def tq_from_se3(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation, (x, y, z, w) quaternion) of pose(s)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), rot_to_quat(T[..., :3, :3])


def se3_inverse(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return se3(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a pose for rotation-first tangents (w, v): T exp(ξ) T⁻¹ = exp(Ad_T ξ)."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3], Ad[3:, 3:], Ad[3:, :3] = R, R, hat(t) @ R
    return Ad


def relative_se3(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """inv(T_a) @ T_b: the motion from pose a to pose b, expressed in a."""
    return se3_inverse(T_a) @ np.asarray(T_b, dtype=np.float64)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one 4x4 pose to an (N, 3) array of points."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices from rotation vectors (radians)."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat(w)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (radians, |w| <= pi) from rotation matrices; robust near 0 and pi."""
    q = rot_to_quat(R)
    v, w = q[..., :3], q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    scale = np.where(s < _EPS, 2.0 / np.maximum(w, _EPS), angle / np.maximum(s, _EPS))
    return v * scale[..., None]


def _so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat(w)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) + a * K + b * (K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Pose(s) from tangent vectors (wx, wy, wz, vx, vy, vz), the exact SE(3) exponential."""
    xi = np.asarray(xi, dtype=np.float64)
    w, v = xi[..., :3], xi[..., 3:]
    return se3(so3_exp(w), (_so3_left_jacobian(w) @ v[..., None])[..., 0])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Tangent vectors (rotation first) of pose(s); inverse of `se3_exp`."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    t = T[..., :3, 3]
    # v = J⁻¹ t with the closed-form inverse left Jacobian I - K/2 + c K², K = [w]x,
    # c = (1 - (θ/2) cot(θ/2)) / θ² (its series near 0; finite up to θ = π)
    theta = np.linalg.norm(w, axis=-1)[..., None]
    small = theta < 1e-2
    half = np.where(small, 1.0, theta) / 2.0
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0 + theta**4 / 30240.0,
                 (1.0 - half / np.tan(half)) / np.where(small, 1.0, theta) ** 2)
    wt = np.cross(w, t)
    v = t - 0.5 * wt + c * np.cross(w, wt)
    return np.concatenate([w, v], axis=-1)


def rpy_to_rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation from fixed-axis roll, pitch, yaw (radians): Rz(yaw) Ry(pitch) Rx(roll), as ROS."""
    Rz = so3_exp(np.array([0.0, 0.0, yaw]))
    Ry = so3_exp(np.array([0.0, pitch, 0.0]))
    Rx = so3_exp(np.array([roll, 0.0, 0.0]))
    return Rz @ Ry @ Rx


def rot_to_rpy(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in radians of rotation(s), the inverse of `rpy_to_rot`."""
    R = np.asarray(R, dtype=np.float64)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def interpolate_se3(T_a: np.ndarray, T_b: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """Poses between T_a (alpha=0) and T_b (alpha=1): slerp on rotation, lerp on translation."""
    alpha = np.asarray(alpha, dtype=np.float64)
    T_a = np.asarray(T_a, dtype=np.float64)
    T_b = np.asarray(T_b, dtype=np.float64)
    dw = so3_log(np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_b[..., :3, :3])
    R = T_a[..., :3, :3] @ so3_exp(alpha[..., None] * dw)
    t = T_a[..., :3, 3] + alpha[..., None] * (T_b[..., :3, 3] - T_a[..., :3, 3])
    return se3(R, t)


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """n rotations uniform on SO(3) (normalized Gaussian quaternions), not uniform Euler angles."""
    q = rng.standard_normal((n, 4))
    return quat_to_rot(q / np.linalg.norm(q, axis=1, keepdims=True))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in radians, in [0, pi]."""
    return np.linalg.norm(so3_log(R), axis=-1)


def symmetric_from_upper(upper: np.ndarray, size: int) -> np.ndarray:
    """The symmetric size x size matrix whose upper triangle, row by row, is `upper` (how the
    device's moment sums come back: kernels/particle_stats)."""
    out = np.zeros((size, size))
    out[np.triu_indices(size)] = upper
    return out + np.triu(out, 1).T
