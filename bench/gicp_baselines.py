"""Baselines for the batched GICP bench that do the same arithmetic as kernels/gicp.py.

One Gauss-Newton iteration of every pose: each source point is placed at the pose, looked up
in the one voxel that holds it (no distance threshold, a miss weighs nothing), and adds
JᵀMJ, JᵀMe and ½eᵀMe with M = (C_B + R C_A Rᵀ)⁻¹ and J = [R hat(μ_A), −R] (rotation first,
right perturbation), accumulated in the centred form [hat(Rμ_A), −I] and rotated once per
pose, as the kernel does; then the Jacobi-scaled, 1e-6-damped system is solved by Cholesky
and the pose retracted, T exp(δ). Everything in float32, source covariances in the plane form
αI + β nnᵀ the kernel uses (batch_gicp.plane_form).

- `numba_iterate`: compiled (LLVM, like Taichi's cpu backend), parallel over poses on every
  thread, each map an open-addressing hash table with linear probing (the kernel's layout
  and hash), no Python per pose. What a C++ implementation of the same loop would be.
- `numpy_iterate`: the same numbers vectorized in NumPy over blocks of poses (a lookup is a
  binary search in the sorted voxel keys of all maps); what one writes without a compiler.

`VoxelMaps` builds the maps from points and covariances in float64 (mean of the points,
average of their covariances, as kernels/voxel_hash.py) and stores them in float32.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

KEY_BITS = 21
KEY_BIAS = 1 << (KEY_BITS - 1)
EMPTY = -1
F32 = np.float32


def pack_keys(coords: np.ndarray) -> np.ndarray:
    """(n, 3) int voxel coordinates -> int64 keys (21 bits each)."""
    c = coords.astype(np.int64) + KEY_BIAS
    return (c[..., 0] << 42) | (c[..., 1] << 21) | c[..., 2]


class VoxelMaps:
    """Gaussian voxel maps (mean, averaged covariance) of several point sets at one voxel size,
    as a hash table per map (Numba) and as one sorted key array (NumPy)."""

    def __init__(self, voxel_size_m: float, buckets_per_map: int, num_maps: int):
        self.res = F32(voxel_size_m)
        self.buckets = buckets_per_map
        self.num_maps = num_maps
        self.table_keys = np.full(num_maps * buckets_per_map, EMPTY, np.int64)
        self.table_vox = np.full(num_maps * buckets_per_map, -1, np.int32)
        self._means, self._covs, self._keys, self._map_ids = [], [], [], []
        self.num_voxels = np.zeros(num_maps, np.int64)

    def insert(self, map_id: int, points: np.ndarray, covs: np.ndarray) -> None:
        """Fill map `map_id` (once) from points (n, 3) and covariances (n, 3, 3)."""
        p32 = points.astype(np.float32)
        coords = np.floor(p32 / self.res).astype(np.int64)  # f32, as the kernel's floor
        keys, inverse = np.unique(pack_keys(coords), return_inverse=True)
        inverse = inverse.ravel()
        count = np.bincount(inverse, minlength=len(keys)).astype(np.float64)
        means = np.stack([np.bincount(inverse, points[:, a], len(keys)) for a in range(3)], 1)
        flat = covs.reshape(-1, 9)
        avg = np.stack([np.bincount(inverse, flat[:, a], len(keys)) for a in range(9)], 1)
        first = sum(len(k) for k in self._keys)
        self._means.append((means / count[:, None]).astype(np.float32))
        self._covs.append((avg / count[:, None]).astype(np.float32).reshape(-1, 3, 3))
        self._keys.append(keys)
        self._map_ids.append(np.full(len(keys), map_id, np.int64))
        self.num_voxels[map_id] = len(keys)
        if not _insert_table(self.table_keys, self.table_vox, keys, first, map_id,
                             self.buckets):
            raise RuntimeError(f"map {map_id}: hash table full ({self.buckets} buckets)")

    def finish(self) -> None:
        """Concatenate the voxels and sort the (map, key) pairs for the NumPy lookup."""
        self.means = np.concatenate(self._means)
        covs = np.concatenate(self._covs)
        self.cov_rows = np.ascontiguousarray(
            covs[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]], np.float32)  # xx xy xz yy yz zz
        keys = np.concatenate(self._keys)
        map_ids = np.concatenate(self._map_ids)
        # NumPy lookup: 16 bits per coordinate and the map id above them
        c = unpack_keys(keys) + (1 << 15)
        if (c < 0).any() or (c >= 1 << 16).any() or self.num_maps >= 1 << 15:
            raise ValueError("maps too large for the NumPy baseline's 16-bit coordinates")
        wide = (map_ids << 48) | (c[:, 0] << 32) | (c[:, 1] << 16) | c[:, 2]
        order = np.argsort(wide)
        self.sorted_keys, self.sorted_vox = wide[order], order.astype(np.int64)
        self._means = self._covs = self._keys = self._map_ids = None


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    mask = (1 << KEY_BITS) - 1
    return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], 1) - KEY_BIAS


@nb.njit(inline="always")
def _slot(cx, cy, cz, probe, map_id, buckets):
    """kernels/voxel_hash.probe_slot in int64 arithmetic masked to 32 bits."""
    m32 = 0xFFFFFFFF
    h = (cx * 73856093 + cy * 19349669 + cz * 83492791) & m32
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & m32
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & m32
    h ^= h >> 16
    return map_id * buckets + ((h + probe) & (buckets - 1))


@nb.njit(cache=True)
def _insert_table(table_keys, table_vox, keys, first, map_id, buckets):
    mask = (1 << KEY_BITS) - 1
    for i in range(len(keys)):
        k = keys[i]
        cx = ((k >> 42) & mask) - KEY_BIAS
        cy = ((k >> 21) & mask) - KEY_BIAS
        cz = (k & mask) - KEY_BIAS
        placed = False
        for probe in range(buckets):
            s = _slot(cx, cy, cz, probe, map_id, buckets)
            if table_keys[s] == EMPTY:
                table_keys[s] = k
                table_vox[s] = first + i
                placed = True
                break
        if not placed:
            return False
    return True


@nb.njit(inline="always")
def _lookup(table_keys, table_vox, cx, cy, cz, map_id, buckets):
    key = ((cx + KEY_BIAS) << 42) | ((cy + KEY_BIAS) << 21) | (cz + KEY_BIAS)
    for probe in range(buckets):
        s = _slot(cx, cy, cz, probe, map_id, buckets)
        k = table_keys[s]
        if k == EMPTY:
            return -1
        if k == key:
            return table_vox[s]
    return -1


@nb.njit(inline="always")
def _rotate_sym(R, s, out):
    """out = Rᵀ S R for the symmetric S given as its upper triangle s (xx xy xz yy yz zz)."""
    S = np.empty((3, 3), np.float32)
    S[0, 0], S[0, 1], S[0, 2] = s[0], s[1], s[2]
    S[1, 0], S[1, 1], S[1, 2] = s[1], s[3], s[4]
    S[2, 0], S[2, 1], S[2, 2] = s[2], s[4], s[5]
    _rt_x_r(R, S, out)


@nb.njit(inline="always")
def _rt_x_r(R, X, out):
    """out = Rᵀ X R (3x3, unrolled: no BLAS call per pose)."""
    for i in range(3):
        for j in range(3):
            acc = F32(0.0)
            for a in range(3):
                for b in range(3):
                    acc += R[a, i] * X[a, b] * R[b, j]
            out[i, j] = acc


@nb.njit(inline="always")
def _solve_step(H, b):
    """δ = −D (D H D + 1e-6 I)⁻¹ D b, Cholesky (kernels/gicp.damped_step)."""
    d = np.empty(6, np.float32)
    for i in range(6):
        d[i] = F32(1.0) / math.sqrt(max(H[i, i], F32(1e-20)))
    A = np.empty((6, 6), np.float32)
    g = np.empty(6, np.float32)
    for i in range(6):
        g[i] = -d[i] * b[i]
        for j in range(6):
            A[i, j] = d[i] * H[i, j] * d[j]
        A[i, i] += F32(1e-6)
    L = np.zeros((6, 6), np.float32)
    for j in range(6):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        dj = math.sqrt(max(s, F32(1e-12)))
        L[j, j] = dj
        for i in range(j + 1, 6):
            s2 = A[i, j]
            for k in range(j):
                s2 -= L[i, k] * L[j, k]
            L[i, j] = s2 / dj
    y = np.empty(6, np.float32)
    for i in range(6):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = np.empty(6, np.float32)
    for ii in range(6):
        i = 5 - ii
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return d * x


@nb.njit(inline="always")
def _retract(R, t, delta):
    """R, t <- T exp(δ) (SO(3) exp and its left Jacobian on the translation)."""
    wx, wy, wz = delta[0], delta[1], delta[2]
    th2 = wx * wx + wy * wy + wz * wz
    th = math.sqrt(th2)
    if th < F32(1e-4):
        A, B, C = F32(1.0), F32(0.5), F32(1.0 / 6.0)
    else:
        A = math.sin(th) / th
        B = (F32(1.0) - math.cos(th)) / th2
        C = (th - math.sin(th)) / (th2 * th)
    W = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]], np.float32)
    W2 = np.zeros((3, 3), np.float32)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                W2[i, j] += W[i, k] * W[k, j]
    dR = np.empty((3, 3), np.float32)
    V = np.empty((3, 3), np.float32)
    for i in range(3):
        for j in range(3):
            eye = F32(1.0) if i == j else F32(0.0)
            dR[i, j] = eye + A * W[i, j] + B * W2[i, j]
            V[i, j] = eye + B * W[i, j] + C * W2[i, j]
    dt = np.zeros(3, np.float32)
    for i in range(3):
        for j in range(3):
            dt[i] += V[i, j] * delta[3 + j]
    Rn = np.zeros((3, 3), np.float32)
    for i in range(3):
        for j in range(3):
            t[i] += R[i, j] * dt[j]
            for k in range(3):
                Rn[i, j] += R[i, k] * dR[k, j]
    R[:, :] = Rn


@nb.njit(inline="always")
def _linearize_pose(R, t, pts, plane, map_id, res, keys, vox, means, cov_rows, buckets,
                    Hc, bc):
    """Centred sums of one pose (Hc: [[rr, −trᵀ], [−tr, tt]] blocks, bc: [b_r, −b_t]) ->
    (error, inliers)."""
    S_rr = np.zeros(6, np.float32)
    S_tr = np.zeros((3, 3), np.float32)
    S_tt = np.zeros(6, np.float32)
    b_r = np.zeros(3, np.float32)
    b_t = np.zeros(3, np.float32)
    err = F32(0.0)
    n = 0
    inv_res = F32(1.0) / res
    for j in range(pts.shape[0]):
        px, py, pz = pts[j, 0], pts[j, 1], pts[j, 2]
        qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz
        qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz
        qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz
        xx, xy, xz = qx + t[0], qy + t[1], qz + t[2]
        v = _lookup(keys, vox, math.floor(xx * inv_res), math.floor(xy * inv_res),
                    math.floor(xz * inv_res), map_id, buckets)
        if v < 0:
            continue
        nx, ny, nz, al, be = plane[j, 0], plane[j, 1], plane[j, 2], plane[j, 3], plane[j, 4]
        rx = R[0, 0] * nx + R[0, 1] * ny + R[0, 2] * nz
        ry = R[1, 0] * nx + R[1, 1] * ny + R[1, 2] * nz
        rz = R[2, 0] * nx + R[2, 1] * ny + R[2, 2] * nz
        cb = cov_rows[v]
        c0 = al + be * rx * rx + cb[0]
        c1 = be * rx * ry + cb[1]
        c2 = be * rx * rz + cb[2]
        c3 = al + be * ry * ry + cb[3]
        c4 = be * ry * rz + cb[4]
        c5 = al + be * rz * rz + cb[5]
        m0, m1, m2 = c3 * c5 - c4 * c4, c2 * c4 - c1 * c5, c1 * c4 - c2 * c3
        m3, m4, m5 = c0 * c5 - c2 * c2, c1 * c2 - c0 * c4, c0 * c3 - c1 * c1
        inv_det = F32(1.0) / (c0 * m0 + c1 * m1 + c2 * m2)
        m0, m1, m2, m3, m4, m5 = (m0 * inv_det, m1 * inv_det, m2 * inv_det, m3 * inv_det,
                                  m4 * inv_det, m5 * inv_det)
        ex, ey, ez = means[v, 0] - xx, means[v, 1] - xy, means[v, 2] - xz
        mex = m0 * ex + m1 * ey + m2 * ez
        mey = m1 * ex + m3 * ey + m4 * ez
        mez = m2 * ex + m4 * ey + m5 * ez
        # rows of M hat(q): (row i of M) x q
        a0x, a0y, a0z = m1 * qz - m2 * qy, m2 * qx - m0 * qz, m0 * qy - m1 * qx
        a1x, a1y, a1z = m3 * qz - m4 * qy, m4 * qx - m1 * qz, m1 * qy - m3 * qx
        a2x, a2y, a2z = m4 * qz - m5 * qy, m5 * qx - m2 * qz, m2 * qy - m4 * qx
        S_rr[0] += qz * a1x - qy * a2x
        S_rr[1] += qz * a1y - qy * a2y
        S_rr[2] += qz * a1z - qy * a2z
        S_rr[3] += qx * a2y - qz * a0y
        S_rr[4] += qx * a2z - qz * a0z
        S_rr[5] += qy * a0z - qx * a1z
        S_tr[0, 0] += a0x
        S_tr[0, 1] += a0y
        S_tr[0, 2] += a0z
        S_tr[1, 0] += a1x
        S_tr[1, 1] += a1y
        S_tr[1, 2] += a1z
        S_tr[2, 0] += a2x
        S_tr[2, 1] += a2y
        S_tr[2, 2] += a2z
        S_tt[0] += m0
        S_tt[1] += m1
        S_tt[2] += m2
        S_tt[3] += m3
        S_tt[4] += m4
        S_tt[5] += m5
        b_r[0] += mey * qz - mez * qy
        b_r[1] += mez * qx - mex * qz
        b_r[2] += mex * qy - mey * qx
        b_t[0] += mex
        b_t[1] += mey
        b_t[2] += mez
        err += F32(0.5) * (ex * mex + ey * mey + ez * mez)
        n += 1
    # H = Dᵀ H_c D, b = Dᵀ b_c with D = diag(R, R), block by block
    blk = np.empty((3, 3), np.float32)
    _rotate_sym(R, S_rr, blk)
    Hc[:3, :3] = blk
    _rotate_sym(R, S_tt, blk)
    Hc[3:, 3:] = blk
    _rt_x_r(R, -S_tr.T.copy(), blk)
    Hc[:3, 3:] = blk
    Hc[3:, :3] = blk.T
    for i in range(3):
        bc[i] = R[0, i] * b_r[0] + R[1, i] * b_r[1] + R[2, i] * b_r[2]
        bc[3 + i] = -(R[0, i] * b_t[0] + R[1, i] * b_t[1] + R[2, i] * b_t[2])
    return err, n


@nb.njit(parallel=True, fastmath=True, cache=True)
def numba_iterate(R, t, pts, plane, map_of, res, keys, vox, means, cov_rows, buckets,
                  H_out, b_out, e_out, n_out):
    """One GN iteration of every pose (parallel over poses): H, b, error, inliers at (R, t),
    then (R, t) moved in place by the step (kept where no point found a voxel)."""
    for g in nb.prange(R.shape[0]):
        Rg = R[g]
        tg = t[g]
        H = H_out[g]
        b = b_out[g]
        err, n = _linearize_pose(Rg, tg, pts, plane, map_of[g], res, keys, vox, means,
                                 cov_rows, buckets, H, b)
        e_out[g] = err
        n_out[g] = n
        if n > 0:
            _retract(Rg, tg, _solve_step(H, b))


def numpy_iterate(R, t, pts, plane, map_of, maps: VoxelMaps, block: int = 64):
    """`numba_iterate` in vectorized NumPy, `block` poses at a time; returns H, b, error,
    inliers and updates R, t in place."""
    G = len(R)
    H_all = np.zeros((G, 6, 6), np.float32)
    b_all = np.zeros((G, 6), np.float32)
    e_all = np.zeros(G, np.float32)
    n_all = np.zeros(G, np.int64)
    for s in range(0, G, block):
        sl = slice(s, min(G, s + block))
        H_all[sl], b_all[sl], e_all[sl], n_all[sl] = _numpy_linearize(
            R[sl], t[sl], pts, plane, map_of[sl], maps)
    _numpy_step(R, t, H_all, b_all, n_all)
    return H_all, b_all, e_all, n_all


def _numpy_linearize(R, t, pts, plane, map_of, maps: VoxelMaps):
    q = np.einsum("gij,nj->gni", R, pts)  # (g, n, 3)
    x = q + t[:, None, :]
    c = np.floor(x * (F32(1.0) / maps.res)).astype(np.int64) + (1 << 15)
    wide = (map_of[:, None] << 48) | (c[..., 0] << 32) | (c[..., 1] << 16) | c[..., 2]
    pos = np.minimum(np.searchsorted(maps.sorted_keys, wide), len(maps.sorted_keys) - 1)
    hit = maps.sorted_keys[pos] == wide
    v = maps.sorted_vox[pos]
    rn = np.einsum("gij,nj->gni", R, plane[:, :3])
    al, be = plane[:, 3], plane[:, 4]
    cb = maps.cov_rows[v]  # (g, n, 6)
    c0 = al + be * rn[..., 0] ** 2 + cb[..., 0]
    c1 = be * rn[..., 0] * rn[..., 1] + cb[..., 1]
    c2 = be * rn[..., 0] * rn[..., 2] + cb[..., 2]
    c3 = al + be * rn[..., 1] ** 2 + cb[..., 3]
    c4 = be * rn[..., 1] * rn[..., 2] + cb[..., 4]
    c5 = al + be * rn[..., 2] ** 2 + cb[..., 5]
    m = np.stack([c3 * c5 - c4 * c4, c2 * c4 - c1 * c5, c1 * c4 - c2 * c3,
                  c0 * c5 - c2 * c2, c1 * c2 - c0 * c4, c0 * c3 - c1 * c1], -1)
    det = c0 * m[..., 0] + c1 * m[..., 1] + c2 * m[..., 2]
    m *= (np.where(hit, F32(1.0), F32(0.0)) / np.where(hit, det, F32(1.0)))[..., None]
    M = m[..., [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(*m.shape[:-1], 3, 3)
    e = maps.means[v] - x
    Me = np.einsum("gnij,gnj->gni", M, e)
    A = np.cross(M, q[:, :, None, :])  # rows of M hat(q)
    rr = -np.cross(q[:, :, :, None], A, axis=2)  # hat(q)ᵀ M hat(q) = −hat(q) (M hat(q))
    S_rr, S_tr, S_tt = rr.sum(1), A.sum(1), M.sum(1)
    b_r, b_t = np.cross(Me, q).sum(1), Me.sum(1)
    Rt = np.swapaxes(R, 1, 2)
    H = np.empty((len(R), 6, 6), np.float32)
    H[:, :3, :3] = Rt @ S_rr @ R
    H[:, 3:, 3:] = Rt @ S_tt @ R
    H[:, :3, 3:] = Rt @ -np.swapaxes(S_tr, 1, 2) @ R
    H[:, 3:, :3] = np.swapaxes(H[:, :3, 3:], 1, 2)
    b = np.concatenate([(Rt @ b_r[..., None])[..., 0], -(Rt @ b_t[..., None])[..., 0]], 1)
    err = F32(0.5) * (e * Me).sum((1, 2))
    return H, b, err, hit.sum(1)


def _numpy_step(R, t, H, b, n):
    d = F32(1.0) / np.sqrt(np.maximum(np.diagonal(H, axis1=1, axis2=2), F32(1e-20)))
    A = d[:, :, None] * H * d[:, None, :] + F32(1e-6) * np.eye(6, dtype=np.float32)
    ok = n > 0
    A[~ok] = np.eye(6, dtype=np.float32)
    L = np.linalg.cholesky(A)
    y = np.linalg.solve(L, (-d * b)[..., None])
    delta = np.where(ok[:, None], d * np.linalg.solve(np.swapaxes(L, 1, 2), y)[..., 0], 0)
    w, v = delta[:, :3].astype(np.float32), delta[:, 3:].astype(np.float32)
    th2 = (w * w).sum(1)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, F32(1.0), th)
    a = np.where(small, F32(1.0), np.sin(ths) / ths)
    bb = np.where(small, F32(0.5), (1 - np.cos(ths)) / ths**2)
    cc = np.where(small, F32(1 / 6), (ths - np.sin(ths)) / ths**3)
    W = np.zeros((len(w), 3, 3), np.float32)
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W -= np.swapaxes(W, 1, 2)
    W2 = W @ W
    eye = np.eye(3, dtype=np.float32)
    dR = eye + a[:, None, None] * W + bb[:, None, None] * W2
    V = eye + bb[:, None, None] * W + cc[:, None, None] * W2
    t += (R @ (V @ v[..., None]))[..., 0]
    R[:] = R @ dR
