"""Trajectory accuracy: timestamp association, Umeyama alignment, ATE and RPE.

Pure numpy, written to give the same numbers as evo 1.38 (`evo_ape`/`evo_rpe`, or its
Python API) on the same files: association as `sync.associate_trajectories(ref, est)`,
alignment as `traj.align(ref, correct_scale)` / `traj.align_origin(ref)`, ATE as
`metrics.APE` (translation_part, rotation_angle_deg) and RPE as `metrics.RPE` with
consecutive pairs picked on the aligned estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core.errors import ConfigError, TrajectoryError
from mcl3d.core.geometry import relative_se3, rotation_angle, se3, se3_inverse
from mcl3d.io.trajectory import Trajectory, detect_format, read_kitti, read_tum

ALIGNMENTS = ("se3", "sim3", "origin", "none")
RPE_UNITS = ("m", "frames")


@dataclass
class ErrorStats:
    """Summary of a set of errors, named as in evo's statistics."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        return cls(rmse=float(np.sqrt(np.mean(e**2))), mean=float(np.mean(e)),
                   median=float(np.median(e)), std=float(np.std(e)), min=float(np.min(e)),
                   max=float(np.max(e)))

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


@dataclass(eq=False)
class Association:
    """Pose pairs whose stamps are nearest within `max_diff_s` (indices into each input)."""

    ref_indices: np.ndarray
    est_indices: np.ndarray
    ref_stamps_s: np.ndarray
    est_stamps_s: np.ndarray
    ref_poses: np.ndarray
    est_poses: np.ndarray
    max_diff_s: float

    def __len__(self) -> int:
        return int(self.ref_indices.shape[0])


def _nearest_within(short_s: np.ndarray, long_s: np.ndarray,
                    max_diff_s: float) -> tuple[np.ndarray, np.ndarray]:
    """evo's matching_time_indices for sorted stamps: nearest long stamp, ties to the earlier."""
    inside = (short_s >= long_s[0] - max_diff_s) & (short_s <= long_s[-1] + max_diff_s)
    short_idx = np.flatnonzero(inside)
    s = short_s[short_idx]
    upper = np.minimum(np.searchsorted(long_s, s, side="right"), len(long_s) - 1)
    diff_ub = long_s[upper] - s
    diff_lb = np.where(upper > 0, s - long_s[np.maximum(upper - 1, 0)], np.inf)
    take_ub = (diff_ub <= max_diff_s) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff_s) & (diff_lb <= diff_ub)
    keep = take_ub | take_lb
    return short_idx[keep], np.where(take_ub, upper, upper - 1)[keep]


def associate(ref: Trajectory, est: Trajectory, max_diff_s: float = 0.01,
              ref_name: str = "the reference", est_name: str = "the estimate") -> Association:
    """Pair each pose of the shorter trajectory with the nearest-in-time pose of the other."""
    if not max_diff_s >= 0:
        raise ConfigError(f"the largest stamp difference must be >= 0 seconds, got {max_diff_s}",
                          setting="t_max_diff")
    for traj, name in ((ref, ref_name), (est, est_name)):
        if len(traj) == 0:
            raise TrajectoryError(f"{name} has no poses")
    if len(est) > len(ref):
        ref_idx, est_idx = _nearest_within(ref.stamps_s, est.stamps_s, max_diff_s)
    else:
        est_idx, ref_idx = _nearest_within(est.stamps_s, ref.stamps_s, max_diff_s)
    if ref_idx.size == 0:
        raise TrajectoryError(
            f"no stamps of {est_name} ({est.stamps_s[0]:.3f}..{est.stamps_s[-1]:.3f} s) match "
            f"{ref_name} ({ref.stamps_s[0]:.3f}..{ref.stamps_s[-1]:.3f} s) within "
            f"{max_diff_s:g} s; check that both use the same clock, or allow a larger "
            f"difference", setting="t_max_diff")
    return Association(ref_idx, est_idx, ref.stamps_s[ref_idx], est.stamps_s[est_idx],
                       ref.poses[ref_idx], est.poses[est_idx], float(max_diff_s))


def umeyama(src_xyz: np.ndarray, dst_xyz: np.ndarray,
            with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimizing sum |dst − (s R src + t)|² (Umeyama 1991), as evo computes it.

    Collinear positions leave the rotation about their line free: evo then returns an
    arbitrary one unless the rank is exactly deficient; we refuse with a relative test.
    """
    n = src_xyz.shape[0]
    if n < 3:
        raise TrajectoryError(
            f"Umeyama alignment needs at least 3 associated poses, got {n}; "
            "align by the origin or not at all, or associate more poses", setting="align")
    mean_src, mean_dst = src_xyz.mean(axis=0), dst_xyz.mean(axis=0)
    centered_src, centered_dst = src_xyz - mean_src, dst_xyz - mean_dst
    sigma_src = np.sum(centered_src**2) / n
    cov = centered_dst.T @ centered_src / n
    u, d, vt = np.linalg.svd(cov)
    if d[1] <= max(np.finfo(d.dtype).eps, 1e-12 * d[0]):
        raise TrajectoryError(
            "Umeyama alignment is undetermined: the associated estimate positions lie on one "
            "line or point; align by the origin or not at all", setting="align")
    flip = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        flip[2, 2] = -1.0
    R = u @ flip @ vt
    s = float(np.trace(np.diag(d) @ flip) / sigma_src) if with_scale else 1.0
    return R, mean_dst - s * R @ mean_src, s


@dataclass(eq=False)
class Alignment:
    """x_ref ≈ T_ref_est · scale(x_est): `scale` multiplies est translations first (evo's order)."""

    method: str
    T_ref_est: np.ndarray
    scale: float

    def apply(self, poses: np.ndarray) -> np.ndarray:
        scaled = np.array(poses, dtype=np.float64)
        scaled[:, :3, 3] *= self.scale
        return self.T_ref_est @ scaled


def align(ref_poses: np.ndarray, est_poses: np.ndarray, method: str) -> Alignment:
    """Alignment of associated estimate poses onto the reference: se3, sim3, origin or none."""
    if method not in ALIGNMENTS:
        raise ConfigError(f"unknown alignment {method!r}; use one of {', '.join(ALIGNMENTS)}")
    if method == "none":
        return Alignment(method, np.eye(4), 1.0)
    if method == "origin":
        return Alignment(method, ref_poses[0] @ se3_inverse(est_poses[0]), 1.0)
    R, t, s = umeyama(est_poses[:, :3, 3], ref_poses[:, :3, 3], with_scale=method == "sim3")
    return Alignment(method, se3(R, t), s)


@dataclass(eq=False)
class PoseErrors:
    """Per-pose (ATE) or per-pair (RPE) errors with their stamps, and their statistics."""

    stamps_s: np.ndarray
    translation_errors_m: np.ndarray
    rotation_errors_deg: np.ndarray
    translation_m: ErrorStats
    rotation_deg: ErrorStats

    @classmethod
    def of(cls, stamps_s, translation_errors_m, rotation_errors_deg) -> PoseErrors:
        return cls(stamps_s, translation_errors_m, rotation_errors_deg,
                   ErrorStats.of(translation_errors_m), ErrorStats.of(rotation_errors_deg))


def ate(ref_poses: np.ndarray, est_poses: np.ndarray, stamps_s: np.ndarray) -> PoseErrors:
    """Absolute errors of aligned estimate poses: distance and angle of R_refᵀ R_est."""
    translation = np.linalg.norm(est_poses[:, :3, 3] - ref_poses[:, :3, 3], axis=1)
    rotation = np.rad2deg(rotation_angle(
        np.swapaxes(ref_poses[:, :3, :3], 1, 2) @ est_poses[:, :3, :3]))
    return PoseErrors.of(np.asarray(stamps_s, dtype=np.float64), translation, rotation)


def _pairs_by_frames(n: int, delta: int, all_pairs: bool) -> np.ndarray:
    if all_pairs:
        first = np.arange(max(n - delta, 0))
        return np.stack([first, first + delta], axis=1)
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def _pairs_by_path(positions: np.ndarray, delta_m: float, tol_m: float,
                   all_pairs: bool) -> np.ndarray:
    steps = np.linalg.norm(positions[:-1] - positions[1:], axis=1)
    if all_pairs:
        travelled = np.concatenate(([0.0], np.cumsum(steps)))
        pairs = []
        for i in range(travelled.size - 1):
            miss = np.abs(travelled[i + 1:] - travelled[i] - delta_m)
            j = int(np.argmin(miss))
            if miss[j] <= tol_m:
                pairs.append((i, i + 1 + j))
        return np.array(pairs, dtype=np.int64).reshape(-1, 2)
    ids, path = [0], 0.0
    for i, step in enumerate(steps.tolist(), start=1):
        path += step
        if path >= delta_m:
            ids.append(i)
            path = 0.0
    return np.stack([ids[:-1], ids[1:]], axis=1).astype(np.int64)


@dataclass(eq=False)
class RelativeErrors(PoseErrors):
    """RPE: errors of the motion between pose pairs a fixed distance or frame count apart."""

    delta: float = 1.0
    unit: str = "m"
    all_pairs: bool = False
    pairs: np.ndarray | None = None


def rpe(ref_poses: np.ndarray, est_poses: np.ndarray, stamps_s: np.ndarray, delta: float = 1.0,
        unit: str = "m", all_pairs: bool = False, rel_delta_tol: float = 0.1) -> RelativeErrors:
    """Relative pose error E = (Q_i⁻¹Q_j)⁻¹(P_i⁻¹P_j) over pairs chosen on the estimate P."""
    if unit not in RPE_UNITS:
        raise ConfigError(f"unknown RPE delta unit {unit!r}; use one of {', '.join(RPE_UNITS)}")
    if unit == "frames" and not (float(delta).is_integer() and delta >= 1):
        raise ConfigError(f"the RPE delta in frames must be a whole number >= 1, got {delta}",
                          setting="rpe_delta")
    if unit == "m" and not delta > 0:
        raise ConfigError(f"the RPE delta in metres must be > 0, got {delta}", setting="rpe_delta")
    n = est_poses.shape[0]
    if unit == "frames":
        pairs = _pairs_by_frames(n, int(delta), all_pairs)
    else:
        pairs = _pairs_by_path(est_poses[:, :3, 3], float(delta), delta * rel_delta_tol,
                               all_pairs)
    if pairs.shape[0] == 0:
        travelled = np.linalg.norm(np.diff(est_poses[:, :3, 3], axis=0), axis=1).sum()
        raise TrajectoryError(
            f"RPE delta {delta:g} {unit} gives no pose pairs ({n} associated poses, "
            f"{travelled:.3f} m travelled by the estimate); use a smaller delta",
            setting="rpe_delta")
    i, j = pairs[:, 0], pairs[:, 1]
    E = relative_se3(relative_se3(ref_poses[i], ref_poses[j]),
                     relative_se3(est_poses[i], est_poses[j]))
    translation = np.linalg.norm(E[:, :3, 3], axis=1)
    rotation = np.rad2deg(rotation_angle(E[:, :3, :3]))
    return RelativeErrors(np.asarray(stamps_s, dtype=np.float64)[j], translation, rotation,
                          ErrorStats.of(translation), ErrorStats.of(rotation),
                          delta=float(delta), unit=unit, all_pairs=all_pairs, pairs=pairs)


@dataclass(eq=False)
class Evaluation:
    """Everything `mcl3d eval` reports and plots."""

    num_ref: int
    num_est: int
    association: Association
    alignment: Alignment
    est_aligned_poses: np.ndarray
    ate: PoseErrors
    rpe: RelativeErrors

    def as_dict(self) -> dict:
        """The numbers, JSON-ready (no per-pose arrays)."""
        return {
            "poses": {"reference": self.num_ref, "estimate": self.num_est,
                      "associated": len(self.association),
                      "t_max_diff_s": self.association.max_diff_s},
            "alignment": {"method": self.alignment.method, "scale": self.alignment.scale,
                          "T_ref_est": self.alignment.T_ref_est.tolist()},
            "ate": {"translation_m": self.ate.translation_m.as_dict(),
                    "rotation_deg": self.ate.rotation_deg.as_dict()},
            "rpe": {"delta": self.rpe.delta, "unit": self.rpe.unit,
                    "all_pairs": self.rpe.all_pairs, "pairs": int(self.rpe.pairs.shape[0]),
                    "translation_m": self.rpe.translation_m.as_dict(),
                    "rotation_deg": self.rpe.rotation_deg.as_dict()},
        }


def evaluate(ref: Trajectory, est: Trajectory, *, alignment: str = "none",
             max_diff_s: float = 0.01, rpe_delta: float = 1.0, rpe_unit: str = "m",
             all_pairs: bool = False, ref_name: str = "the reference",
             est_name: str = "the estimate") -> Evaluation:
    """Associate, align, then ATE and RPE of `est` against `ref`: evo's pipeline."""
    if alignment not in ALIGNMENTS:
        raise ConfigError(f"unknown alignment {alignment!r}; use one of {', '.join(ALIGNMENTS)}")
    pairs = associate(ref, est, max_diff_s, ref_name, est_name)
    how = align(pairs.ref_poses, pairs.est_poses, alignment)
    est_aligned = how.apply(pairs.est_poses)
    return Evaluation(
        num_ref=len(ref), num_est=len(est), association=pairs, alignment=how,
        est_aligned_poses=est_aligned,
        ate=ate(pairs.ref_poses, est_aligned, pairs.est_stamps_s),
        rpe=rpe(pairs.ref_poses, est_aligned, pairs.est_stamps_s, rpe_delta, rpe_unit,
                all_pairs))


def read_pair(ref_path, est_path) -> tuple[Trajectory, Trajectory]:
    """Read reference and estimate (TUM or KITTI); KITTI has no stamps, so pair by line."""
    ref_fmt, est_fmt = detect_format(ref_path), detect_format(est_path)
    if ref_fmt != est_fmt:
        kitti, tum = (ref_path, est_path) if ref_fmt == "kitti" else (est_path, ref_path)
        raise TrajectoryError(
            f"{kitti} is a KITTI file (no stamps) but {tum} is TUM, so their poses cannot be "
            "paired in time; give both in TUM format, or both in KITTI with one pose per line")
    if ref_fmt == "tum":
        return read_tum(ref_path), read_tum(est_path)
    ref, est = read_kitti(ref_path), read_kitti(est_path)
    if len(ref) != len(est):
        raise TrajectoryError(
            f"KITTI files carry no stamps, so poses are paired by line, but {est_path} has "
            f"{len(est)} poses and {ref_path} has {len(ref)}; give TUM files with stamps")
    return ref, est
