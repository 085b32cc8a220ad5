"""Device reductions, gathers and the counting sort that keep particle arrays on the device,
against NumPy references on tiny inputs."""

import numpy as np
import pytest


def _scalar(values, dtype=None):
    import taichi as ti

    f = ti.field(dtype or ti.f32, shape=len(values))
    f.from_numpy(np.asarray(values, np.int32 if dtype == ti.i32 else np.float32))
    return f


def _partials(n):
    import taichi as ti

    from mcl3d.kernels.resample import SCAN_BLOCK

    return (ti.Vector.field(2, ti.f32, shape=(n + SCAN_BLOCK - 1) // SCAN_BLOCK),
            ti.field(ti.f32, shape=2))


@pytest.mark.parametrize("n", [1, 5, 300, 1000])
def test_tempered_sums_match_numpy(ti_runtime, n):
    from mcl3d.kernels import particle_stats as ks

    rng = np.random.default_rng(n)
    log_w = rng.normal(scale=20.0, size=n).astype(np.float32) - 3000.0
    inc = rng.normal(scale=2.0, size=n).astype(np.float32)
    coef = -7.5
    x = log_w.astype(np.float64) + coef * inc.astype(np.float64)
    partial, sums = _partials(n)
    ks.tempered_sums(_scalar(log_w), _scalar(inc), n, coef, partial, sums)
    w = np.exp(x - x.max())
    assert float(sums[0]) == pytest.approx(w.sum(), rel=1e-3)
    assert float(sums[1]) == pytest.approx(w @ w, rel=1e-3)


@pytest.mark.parametrize("n", [1, 9, 700])
def test_weighted_sums_and_first_max_match_numpy(ti_runtime, n):
    from mcl3d.kernels import particle_stats as ks
    from mcl3d.kernels.resample import sum_partials

    rng = np.random.default_rng(10 + n)
    w = rng.integers(0, 5, size=n).astype(np.float32)  # ties: the first maximum counts
    a, b = rng.random(n).astype(np.float32), rng.normal(size=n).astype(np.float32)
    partial, sums = _partials(n)
    ks.weighted_partials(_scalar(w), _scalar(a), _scalar(b), n, partial)
    sum_partials(partial, n, sums)
    assert float(sums[0]) == pytest.approx(float(w @ a), rel=1e-5, abs=1e-6)
    assert float(sums[1]) == pytest.approx(float(w @ b), rel=1e-4, abs=1e-5)
    assert ks.first_index_of(_scalar(w), n, float(w.max())) == int(np.argmax(w))
    assert ks.first_index_of(_scalar(w), n, 99.0) == n


def test_gathers_match_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import particle_stats as ks

    rng = np.random.default_rng(3)
    n, k = 50, 12
    pos, quat = rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4))
    idx = rng.integers(0, n, size=k)
    fp, fq = ti.Vector.field(3, ti.f32, shape=n), ti.Vector.field(4, ti.f32, shape=n)
    fp.from_numpy(pos)
    fq.from_numpy(quat.astype(np.float32))
    op, oq = ti.Vector.field(3, ti.f32, shape=k), ti.Vector.field(4, ti.f32, shape=k)
    vals, out = _scalar(pos[:, 0]), ti.field(ti.f32, shape=k)
    fidx = _scalar(idx, ti.i32)
    ks.gather_poses(fp, fq, fidx, k, op, oq)
    ks.gather_values(vals, fidx, k, out)
    assert np.array_equal(op.to_numpy(), pos[idx])
    assert np.allclose(oq.to_numpy(), quat[idx], atol=1e-6)
    assert np.array_equal(out.to_numpy(), pos[idx, 0])


@pytest.mark.parametrize("n, bins", [(1, 4), (40, 7), (2000, 1000)])
def test_counting_sort_groups_by_key(ti_runtime, n, bins):
    """A permutation of 0..n-1 whose keys ascend; within a key every index appears once
    (the order inside a key is free)."""
    import taichi as ti

    from mcl3d.kernels.counting_sort import SCAN_BLOCK, sort_by_key

    rng = np.random.default_rng(n)
    keys = rng.integers(0, bins, size=n)
    starts = ti.field(ti.i32, shape=bins)
    blocks = ti.field(ti.i32, shape=bins // SCAN_BLOCK + 1)
    order = ti.field(ti.i32, shape=n + 3)
    sort_by_key(_scalar(keys, ti.i32), n, starts, blocks, order)
    got = order.to_numpy()[:n]
    assert np.array_equal(np.sort(got), np.arange(n))
    assert np.array_equal(keys[got], np.sort(keys))
    assert np.array_equal(starts.to_numpy(), np.cumsum(np.bincount(keys, minlength=bins)))


def test_factor_kernels_match_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels.particles import apply_factors, log_inverse_parent_factor

    rng = np.random.default_rng(4)
    n = 30
    w, factor = rng.random(n).astype(np.float32), rng.uniform(0.5, 4.0, n).astype(np.float32)
    parent = rng.integers(0, n, size=20)
    fw, ff, log_w = _scalar(w), _scalar(factor), _scalar(np.zeros(n))
    apply_factors(fw, ff, n - 1)
    expected = w * factor
    expected[-1] = w[-1]
    assert np.allclose(fw.to_numpy(), expected, rtol=1e-6)
    log_inverse_parent_factor(ff, _scalar(parent, ti.i32), 20, log_w)
    assert np.allclose(log_w.to_numpy()[:20], -np.log(factor[parent]), atol=1e-6)


def test_cluster_label_kernels_match_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import cluster_labels as kc
    from mcl3d.kernels.particle_stats import sum_vector_partials
    from mcl3d.kernels.resample import SCAN_BLOCK

    rng = np.random.default_rng(8)
    n = 600
    pos = rng.uniform(-2.0, 2.0, size=(n, 3)).astype(np.float32)
    quat = rng.normal(size=(n, 4))
    quat = (quat / np.linalg.norm(quat, axis=1, keepdims=True)).astype(np.float32)
    centres = np.zeros((kc.MAX_CENTRES, 7), np.float32)
    centres[:2, :3] = [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]
    centres[:2, 3:] = quat[[0, 1]]
    fp, fq = ti.Vector.field(3, ti.f32, shape=n), ti.Vector.field(4, ti.f32, shape=n)
    fp.from_numpy(pos)
    fq.from_numpy(quat)
    fc = ti.Vector.field(7, ti.f32, shape=kc.MAX_CENTRES)
    fc.from_numpy(centres)
    label, w = ti.field(ti.i32, shape=n), _scalar(rng.random(n))
    kc.label_by_centres(fp, fq, n, fc, 2, 1.5, 0.8, label)
    expected = np.full(n, -1)
    for c in (1, 0):  # the first centre that fits wins
        near = (np.linalg.norm(pos - centres[c, :3], axis=1) <= 1.5) & (
            np.abs(quat @ centres[c, 3:]) >= 0.8)
        expected[near] = c
    got = label.to_numpy()
    assert np.mean(got == expected) > 0.99 and set(np.unique(got)) == {-1, 0, 1}
    partial = ti.Vector.field(kc.MAX_CENTRES, ti.f32, shape=(n + SCAN_BLOCK - 1) // SCAN_BLOCK)
    total = ti.Vector.field(kc.MAX_CENTRES, ti.f32, shape=1)
    kc.label_weight_partials(w, label, n, partial)
    sum_vector_partials(partial, n, total)
    wh = w.to_numpy()
    np.testing.assert_allclose(total.to_numpy()[0, :2], [wh[got == 0].sum(), wh[got == 1].sum()],
                               rtol=1e-5)
    assert not total.to_numpy()[0, 2:].any()
    table = _scalar([5.0, 2.0, 0.5] + [1.0] * (kc.MAX_CENTRES - 2))
    factor = _scalar(np.full(n, 1.5))
    kc.label_factors(label, n, table, 1, factor)
    np.testing.assert_allclose(factor.to_numpy(), np.maximum(
        np.array([5.0, 2.0, 0.5])[got + 1], 1.5))
    kc.label_factors(label, n, table, 0, factor)
    np.testing.assert_allclose(factor.to_numpy(), np.array([5.0, 2.0, 0.5])[got + 1])
