"""NumPy reference of kernels/covariance.is_scan_line, for the covariance tests."""

import numpy as np

from mcl3d.kernels.covariance import LINE_RATIO, SCAN_LINE_SIN2_SLOPE


def scan_lines(S: np.ndarray) -> np.ndarray:
    """Which scatters (N, 3, 3) are scan lines: λmid < LINE_RATIO λmax and the line within
    30° of the xy plane (S_zz < sin² 30° λmax)."""
    lam = np.linalg.eigvalsh(S)
    return (lam[:, 1] < LINE_RATIO * lam[:, 2]) & (S[:, 2, 2] < SCAN_LINE_SIN2_SLOPE * lam[:, 2])
