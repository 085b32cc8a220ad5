"""Reading and writing recorded logs (MCAP, ROS 1/2 bags) and point-cloud files."""
