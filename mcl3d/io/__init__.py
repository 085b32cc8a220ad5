"""Reading and writing what users bring and take away: logs (MCAP, ROS bags, point-cloud
files, Ouster pcap) in `io.logs`, and trajectories (TUM, KITTI) in `io.trajectory`.
"""
