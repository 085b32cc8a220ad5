"""mcl3d: 6-DoF Monte Carlo localization and Monte Carlo SLAM for 3D LiDAR.

Importing the package is cheap: taichi, open3d and mcap are imported by the modules that
need them, and the CLI imports those inside its commands, so `mcl3d --help` stays instant.
"""

import os
from pathlib import Path

# Any module below may import taichi, which aborts (a C++ assertion) without HOME, as under
# systemd, and prints a banner on import: both are settled before the first such import.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
os.environ.setdefault("HOME", str(Path.home()))

__version__ = "0.1.0"
