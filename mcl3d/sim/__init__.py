"""The simulator behind `mcl3d simulate`: worlds (mesh, worlds), trajectories (spline,
trajectories), sensors (lidars, scan, raycast, imu, wheel_odometry) and the pipeline writing
logs."""
