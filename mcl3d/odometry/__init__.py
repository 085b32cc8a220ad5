"""LiDAR(-inertial) odometry: IMU preintegration, scan-to-model GICP against keyframes, and
the `odometry` pipeline.
"""
