"""The odometry methods `bench_odometry.py` compares, each behind one interface, fed the same
scans: `reset(T_lidar_imu)` per log, `step(stamp_ns, points, times_s, imu_rows)` per scan
(times relative to the header stamp; IMU rows (stamp_s, wx, wy, wz, ax, ay, az) since the
previous scan, as `mcl3d.odometry.scan_feed.LidarImuFeed` pairs them), then `trajectory()`:
(stamps_ns, T_world_lidar) at the scans' header stamps, the first scan's frame as world.

Deskewing is equal: every method gets the per-point times and deskews with its own motion
estimate (mcl3d with its IMU or constant-velocity prediction; KISS-ICP, GenZ-ICP and
small_gicp with the last scan's motion, constant velocity; rko-lio with its IMU). small_gicp
has no deskew of its own, so it gets mcl3d's deskew kernel with its own last motion. Every
method crops to the same 0.5-100 m (mcl3d's defaults); voxel sizes are each method's own
defaults. Pose stamps: KISS-ICP and GenZ-ICP register at mid-sweep (their deskew's reference,
time 0.5 of the normalized sweep) and are moved to the stamp along their own motion, as
`slam_peers.py` does; rko-lio's poses are interpolated at the stamps.
"""

from __future__ import annotations

import numpy as np
from slam_peers import (
    MAX_RANGE_M,
    MIN_RANGE_M,
    _at_stamp,
    _kiss_icp_config,
    _resampled,
    _unit_times,
    _xyzw_xyz,
)

SMALL_GICP_DOWNSAMPLE_M = 0.25  # small_gicp's kitti_odometry.py example
SMALL_GICP_MAP_VOXEL_M = 1.0


class Mcl3dOdometry:
    """mcl3d's `LidarOdometry` (what `mcl3d odometry` runs per scan); device fields are
    allocated once and reused across logs."""

    def __init__(self, use_imu: bool):
        from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig

        self.odo = LidarOdometry(OdometryConfig(use_imu=use_imu, min_range_m=MIN_RANGE_M,
                                                max_range_m=MAX_RANGE_M))

    def reset(self, T_lidar_imu):
        self.odo.reset(T_lidar_imu)
        self.stamps, self.poses = [], []

    def step(self, stamp_ns, points, times, imu):
        frame = self.odo.step(points, times, stamp_ns, imu)
        self.stamps.append(stamp_ns)
        self.poses.append(frame.T_world_lidar)

    def trajectory(self):
        return np.array(self.stamps), np.stack(self.poses)


class KissIcp:
    """KISS-ICP 1.3 with its deskew on, normalized [0, 1] point times."""

    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        from kiss_icp.kiss_icp import KissICP

        cfg = _kiss_icp_config(MAX_RANGE_M, None)  # voxel: max_range / 100, its pipeline's rule
        cfg.registration.max_num_threads = self.threads
        self.odo = KissICP(cfg)
        self.stamps, self.poses = [], []

    def step(self, stamp_ns, points, times, imu):
        unit, stamp_unit = _unit_times(times)
        self.odo.register_frame(points, unit)
        self.stamps.append(stamp_ns)
        self.poses.append(_at_stamp(self.odo.last_pose, self.odo.last_delta, stamp_unit))

    def trajectory(self):
        return np.array(self.stamps), np.stack(self.poses)


class GenzIcp:
    """GenZ-ICP 0.3 (point-to-plane + point-to-point by planarity), deskew on, default
    voxel 0.3 m; its Python wrapper exposes no thread count (TBB takes every core)."""

    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        from genz_icp.config import GenZConfig
        from genz_icp.genz_icp import GenZICP

        cfg = GenZConfig()
        cfg.data.deskew = True
        cfg.data.max_range, cfg.data.min_range = MAX_RANGE_M, MIN_RANGE_M
        self.odo = GenZICP(cfg)
        self.stamps, self.poses, self.last = [], [], np.eye(4)

    def step(self, stamp_ns, points, times, imu):
        unit, stamp_unit = _unit_times(times)
        self.odo.register_frame(points, unit)
        pose = np.array(self.odo.last_pose)
        delta = np.linalg.inv(self.last) @ pose  # its deskew's motion (the last scan's)
        self.last = pose
        self.stamps.append(stamp_ns)
        self.poses.append(_at_stamp(pose, delta, stamp_unit))

    def trajectory(self):
        return np.array(self.stamps), np.stack(self.poses)


class RkoLio:
    """rko-lio 0.4 (LiDAR-inertial), lidar as base frame, the log's IMU extrinsic, deskew
    on; absolute per-point ns stamps. Its pipeline needs IMU samples up to a scan's end
    before that scan (what its Sequencer ensures), and the samples paired with scan i end at
    scan i's stamp, the start of its sweep: so scan i is registered in step i + 1, after
    the samples covering its sweep (one scan of latency; the last scan is left out)."""

    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        from rko_lio.lio_pipeline import LIOPipeline, PipelineConfig

        self.pipe = LIOPipeline(PipelineConfig.from_dict({
            "lio": {"max_range": MAX_RANGE_M, "min_range": MIN_RANGE_M, "deskew": True,
                    "max_num_threads": self.threads},
            "extrinsic_imu2base_quat_xyzw_xyz": _xyzw_xyz(T_lidar_imu),
            "extrinsic_lidar2base_quat_xyzw_xyz": _xyzw_xyz(np.eye(4))}))
        self.stamps, self.waiting, self.last_imu_ns = [], None, -1

    def step(self, stamp_ns, points, times, imu):
        for row in imu if imu is not None else ():
            imu_ns = round(row[0] * 1e9)
            if imu_ns > self.last_imu_ns:  # each scan's rows repeat the previous scan's last
                self.pipe.add_imu(imu_ns, np.asarray(row[4:7]), np.asarray(row[1:4]))
                self.last_imu_ns = imu_ns
        if self.waiting is not None:
            self.pipe.register_scan(*self.waiting)
        abs_ns = stamp_ns + np.rint(times * 1e9).astype(np.int64)
        self.waiting = (int(abs_ns.min()), int(abs_ns.max()), points, abs_ns)
        self.stamps.append(stamp_ns)

    def trajectory(self):
        run = _resampled("rko-lio", self.pipe.lio.poses_with_timestamps(),
                         np.array(self.stamps), 0.0)
        return run.stamps_ns, run.poses


class SmallGicp:
    """small_gicp 1.0 scan-to-model as its `kitti_odometry.py` example drives it (0.25 m
    downsampling, GaussianVoxelMap 1.0 m with LRU, GICP), plus a deskew: mcl3d's kernel with
    small_gicp's own last motion (constant velocity), to the middle of the sweep, where the
    scan is registered (as KISS-ICP does: a velocity error then barely moves the registered
    pose; deskewed to the sweep's start, the error fed back and the poses oscillated apart);
    the pose is moved to the header stamp along the same motion."""

    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        import small_gicp

        self.voxelmap = small_gicp.GaussianVoxelMap(SMALL_GICP_MAP_VOXEL_M)
        self.voxelmap.set_lru(horizon=100, clear_cycle=10)
        self.T_world_mid, self.T_last_current = np.eye(4), np.eye(4)  # at mid-sweep times
        self.stamps, self.poses, self.last_mid_s = [], [], None

    def step(self, stamp_ns, points, times, imu):
        import small_gicp

        from mcl3d.core.geometry import se3_exp, se3_log
        from mcl3d.registration.preprocess import deskew

        t_ref = 0.5 * (float(times.min()) + float(times.max()))
        mid_s = stamp_ns * 1e-9 + t_ref
        twist = np.zeros(6)
        if self.last_mid_s is not None:
            twist = se3_log(self.T_last_current) / max(mid_s - self.last_mid_s, 1e-6)
            points = deskew(points, times - t_ref, twist)
        down, _ = small_gicp.preprocess_points(points, SMALL_GICP_DOWNSAMPLE_M,
                                               num_threads=self.threads)
        if self.voxelmap.size() == 0:
            self.voxelmap.insert(down)
        else:
            result = small_gicp.align(self.voxelmap, down,
                                      self.T_world_mid @ self.T_last_current,
                                      num_threads=self.threads)
            self.T_last_current = np.linalg.inv(self.T_world_mid) @ result.T_target_source
            self.T_world_mid = result.T_target_source
            self.voxelmap.insert(down, self.T_world_mid)
        self.last_mid_s = mid_s
        self.stamps.append(stamp_ns)
        self.poses.append(self.T_world_mid @ se3_exp(-t_ref * twist))

    def trajectory(self):
        stamps, poses = np.array(self.stamps), np.stack(self.poses)
        return stamps, np.linalg.inv(poses[0]) @ poses  # the first scan's frame as world


def methods(threads: int) -> dict:
    """Every method of the bench, LiDAR-only first, by the name its rows carry."""
    return {"mcl3d (no IMU)": Mcl3dOdometry(False), "KISS-ICP": KissIcp(threads),
            "GenZ-ICP": GenzIcp(threads), "small_gicp + deskew": SmallGicp(threads),
            "mcl3d (IMU)": Mcl3dOdometry(True), "rko-lio (IMU)": RkoLio(threads)}


INPUTS = {"mcl3d (no IMU)": "LiDAR", "KISS-ICP": "LiDAR", "GenZ-ICP": "LiDAR",
          "small_gicp + deskew": "LiDAR", "mcl3d (IMU)": "LiDAR + IMU",
          "rko-lio (IMU)": "LiDAR + IMU"}
