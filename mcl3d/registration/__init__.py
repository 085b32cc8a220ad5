"""Scan registration shared by odometry and SLAM: preprocessing (deskew, downsample,
covariances), Gaussian voxel maps, batched GICP over many poses and pairwise `align`.
"""
