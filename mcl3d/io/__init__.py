"""Reading and writing what users bring and take away: logs (MCAP, ROS bags, point-cloud
files, Ouster pcap) in `io.logs`, trajectories (TUM, KITTI) in `io.trajectory`, and a run's
results for Foxglove (result MCAP, live view) in `io.foxglove_results`.
"""
