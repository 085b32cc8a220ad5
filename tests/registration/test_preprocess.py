"""Preprocessing: voxel downsampling, plane-regularized covariances, deskewing."""

from __future__ import annotations

import numpy as np
import pytest
from support.scan_lines import scan_lines

from mcl3d.core.errors import ConfigError, PointCloudError
from mcl3d.core.geometry import se3_exp, transform_points
from mcl3d.registration.preprocess import deskew, estimate_covariances, preprocess, voxel_downsample


def test_voxel_downsample_is_the_mean_per_voxel():
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.2, 0.4], [1.2, 0.1, 0.1], [-0.2, 0.0, 0.0]])
    out = voxel_downsample(pts, 0.5)
    expected = np.array([[0.2, 0.15, 0.25], [1.2, 0.1, 0.1], [-0.2, 0.0, 0.0]])
    assert len(out) == 3
    for row in expected:
        assert np.isclose(out, row).all(axis=1).any()


def reference_covariances(points, k):
    """float64 NumPy reference: scatter of the k nearest, eigenvalues set to (1e-3, 1, 1); the
    identity where the scatter is a scan line."""
    from scipy.spatial import cKDTree

    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]
    d = nb - nb.mean(axis=1, keepdims=True)
    S = np.einsum("nki,nkj->nij", d, d) / k
    _, U = np.linalg.eigh(S)
    out = np.einsum("nij,j,nkj->nik", U, np.array([1e-3, 1.0, 1.0]), U)
    out[scan_lines(S)] = np.eye(3)
    return out


def test_covariance_kernel_matches_numpy(ti_runtime):
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(500, 3)) * [3.0, 2.0, 0.3] + 50.0  # far from the origin
    np.testing.assert_allclose(estimate_covariances(pts, 10), reference_covariances(pts, 10),
                               atol=2e-3)
    # exactly planar neighbourhoods (a zero eigenvalue) are where closed forms break down
    flat = np.c_[rng.uniform(-2, 2, (300, 2)), np.full(300, 3.13)]
    np.testing.assert_allclose(estimate_covariances(flat, 10), np.tile(
        np.diag([1.0, 1.0, 1e-3]), (300, 1, 1)), atol=1e-5)


def test_normals_of_given_scatters_match_numpy(ti_runtime):
    """The kernel's normal (closed form, Jacobi where the two smallest eigenvalues are close)
    for scatters with known spectra: six points ±sqrt(3 λ) u per eigenpair (λ, u). Scan lines
    (λmid < LINE_RATIO λmax, spectra on either side of the bound, at random slopes) get the
    identity."""
    from scipy.spatial.transform import Rotation

    from mcl3d.kernels.covariance import LINE_RATIO, plane_covariances

    spectra = [(0.0, 1.0, 1.0), (1e-4, 0.3, 1.0), (0.02, 0.5, 0.6), (1e-3, 2e-3, 1.0),
               (0.0, 1e-7, 1.0), (0.0, 0.0, 1.0), (1.0, 1.0, 1.0), (1e-4, 0.06, 1.0),
               (1e-4, 0.04, 1.0), (0.01, 0.055, 1.0)]
    R = Rotation.random(8 * len(spectra), random_state=4).as_matrix()
    lam = np.repeat(np.array(spectra), 8, axis=0) * np.geomspace(1e-4, 1e2, len(R))[:, None]
    axes = np.sqrt(3.0 * lam)[:, :, None] * R.transpose(0, 2, 1)  # rows: sqrt(3 λ_j) u_j
    pts = (np.concatenate([axes, -axes], axis=1) + 20.0).reshape(-1, 3)
    out = np.empty((len(R), 3, 3), np.float32)
    plane_covariances(pts.astype(np.float32), np.arange(len(pts), dtype=np.int32).reshape(-1, 6),
                      np.full(len(R), 6, np.int32), len(R), 5, 1e-3, out)
    S = np.einsum("nji,nj,njk->nik", R.transpose(0, 2, 1), lam, R.transpose(0, 2, 1))
    line = scan_lines(S)
    steep = np.repeat([s[1] < LINE_RATIO * s[2] for s in spectra], 8) & ~line  # a disc
    assert line.any() and steep.any() and not line.all()
    np.testing.assert_allclose(out[line], np.tile(np.eye(3), (line.sum(), 1, 1)))
    normal = np.linalg.eigh(out.astype(np.float64))[1][:, :, 0]
    cos = np.abs(np.einsum("ni,ni->n", normal, R[:, :, 0]))
    distinct = np.repeat([s[0] < s[1] and s[1] > 1e-6 * s[2] for s in spectra], 8) & ~line
    assert cos[distinct].min() > 1.0 - 1e-5
    np.testing.assert_allclose(np.linalg.eigvalsh(out[~line].astype(np.float64)),
                               np.tile([1e-3, 1.0, 1.0], ((~line).sum(), 1)), atol=1e-5)


def test_covariance_of_a_plane_is_a_thin_disc_along_it(ti_runtime):
    rng = np.random.default_rng(0)
    uv = rng.uniform(-1, 1, (400, 2))
    normal = np.array([1.0, 2.0, 2.0]) / 3.0
    e1 = np.cross(normal, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    pts = uv[:, :1] * e1 + uv[:, 1:] * e2 + 0.001 * rng.normal(size=(400, 1)) * normal
    covs = estimate_covariances(pts, k_neighbors=10)
    for C in covs[:20]:
        w, U = np.linalg.eigh(C)
        np.testing.assert_allclose(w, [1e-3, 1.0, 1.0], atol=1e-6)
        assert abs(abs(U[:, 0] @ normal) - 1.0) < 0.05


def test_a_scan_line_gets_the_identity_and_a_trunk_a_disc(ti_runtime):
    """A sparse lidar's ring on the ground: alone, its neighbours lie along a line and say
    nothing of the ground's normal (identity); with the next ring close by, a disc. A trunk
    seen by several rings (a steep line, an arc facing the sensor) keeps its disc."""
    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 6.0, 25)
    ring = np.c_[x, 0.002 * rng.normal(size=25), np.full(25, -1.5)]
    np.testing.assert_allclose(estimate_covariances(ring, 10), np.tile(np.eye(3), (25, 1, 1)))
    two_rings = np.vstack([ring, ring + np.array([0.0, 0.6, 0.0])])
    for C in estimate_covariances(two_rings, 10):
        w, U = np.linalg.eigh(C)
        np.testing.assert_allclose(w, [1e-3, 1.0, 1.0], atol=1e-6)
        assert abs(U[2, 0]) > 0.999
    angle = np.linspace(-0.6, 0.6, 5)  # the sensor-facing arc of a 15 cm trunk at x = 6 m
    trunk = np.array([[6.0 - 0.15 * np.cos(a), 0.15 * np.sin(a), z]
                      for z in np.linspace(-1.0, 2.0, 10) for a in angle])
    for C in estimate_covariances(trunk, 10):
        w, U = np.linalg.eigh(C)
        np.testing.assert_allclose(w, [1e-3, 1.0, 1.0], atol=1e-6)
        assert abs(U[0, 0]) > 0.9  # facing the sensor


def test_too_few_neighbours_give_the_identity(ti_runtime):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5.0]])
    np.testing.assert_allclose(estimate_covariances(pts), np.tile(np.eye(3), (4, 1, 1)))
    # a far point with a distance bound finds only itself: identity, the cluster does not
    cluster = np.random.default_rng(1).normal(size=(30, 3)) * 0.1
    covs = estimate_covariances(np.vstack([cluster, [[50.0, 0, 0]]]), max_neighbor_dist_m=1.0)
    np.testing.assert_allclose(covs[-1], np.eye(3))
    assert np.linalg.eigvalsh(covs[0])[0] == pytest.approx(1e-3, abs=1e-6)


def test_deskew_moves_points_to_the_stamp_frame(ti_runtime):
    rng = np.random.default_rng(2)
    world = rng.uniform(-10, 10, (200, 3))
    twist = np.array([0.0, 0.0, 0.8, 2.0, 0.3, 0.0])  # rad/s, m/s in the sensor frame
    times = rng.uniform(-0.05, 0.05, 200)  # relative to the stamp
    # the sensor at time t sits at exp(t twist) in the stamp frame: what it measured there
    measured = np.array([transform_points(np.linalg.inv(se3_exp(t * twist)), p[None])[0]
                         for t, p in zip(times, world, strict=True)])
    np.testing.assert_allclose(deskew(measured, times, twist), world, atol=2e-5)
    np.testing.assert_allclose(deskew(measured, np.zeros(200), twist), measured, atol=2e-6)


def test_preprocess_crops_and_returns_a_scan(ti_runtime):
    rng = np.random.default_rng(3)
    pts = rng.uniform(-20, 20, (3000, 3))
    scan = preprocess(pts, voxel_size_m=2.0, min_range_m=1.0, max_range_m=15.0)
    r = np.linalg.norm(scan.points, axis=1)
    assert len(scan) == len(scan.covs) > 100 and r.max() <= 15.0
    assert "Scan(" in repr(scan)


def test_bad_input_raises_typed_errors(ti_runtime):
    with pytest.raises(PointCloudError, match="NaN"):
        preprocess(np.array([[0.0, 1.0, np.inf]]))
    with pytest.raises(PointCloudError, match="shape"):
        preprocess(np.zeros((4, 2)))
    with pytest.raises(ConfigError, match="voxel_size_m"):
        voxel_downsample(np.zeros((3, 3)), -1.0)
    with pytest.raises(ConfigError, match="k_neighbors"):
        estimate_covariances(np.zeros((10, 3)), k_neighbors=3)
    with pytest.raises(PointCloudError, match="one time per point"):
        deskew(np.zeros((3, 3)), np.zeros(2), np.zeros(6))
    assert len(preprocess(np.zeros((0, 3)))) == 0
