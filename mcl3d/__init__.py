"""mcl3d: 6-DoF Monte Carlo localization and Monte Carlo SLAM for 3D LiDAR.

Importing the package is cheap: taichi, open3d and mcap are imported by the modules that
need them, so `mcl3d --help` stays instant.
"""

__version__ = "0.1.0"
