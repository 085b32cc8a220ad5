"""LiDAR(-inertial) odometry: IMU preintegration, scan-to-model GICP against keyframes
(lidar_odometry), the scans of a log with their IMU samples (scan_feed, shared with SLAM),
and the `odometry` pipeline with its summary and what it shows in Foxglove (result_view).
"""
