"""Point-cloud maps (no rays, no poses): each point's normal and local spacing from its k
nearest (voxel_normals' Morton-sorted cells), then its truncation band along the normal.

A point's band is the scans' band (tsdf_band): columns along the normal, a voxel apart,
from behind_m behind the surface to the truncation in front, over a patch of the tangent
plane of half-width `steps` half-voxels (the host sizes it from the local spacing), so
sparse surfaces leave no holes and dense ones (steps 0) write one column per point: 6
voxels a point at 10 cm where a cube of the truncation's radius around it is 729.
"""

import taichi as ti

from mcl3d.kernels.tsdf_band import (
    allocate_patch,
    band_samples,
    flush_slots,
    point_band,
)
from mcl3d.kernels.tsdf_lookup import UNKNOWN, geometry, ivec3, vec3
from mcl3d.kernels.voxel_normals import k_nearest, plane_normal


@ti.kernel
def normals_and_spacing(pts: ti.types.ndarray(dtype=vec3, ndim=1),
                        cells: ti.types.ndarray(dtype=ivec3, ndim=1), first: ti.i32,
                        count: ti.i32, keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
                        starts: ti.types.ndarray(dtype=ti.i32, ndim=1),
                        ends: ti.types.ndarray(dtype=ti.i32, ndim=1),
                        offsets: ti.types.ndarray(dtype=ti.i32, ndim=1), k: ti.i32,
                        min_own: ti.i32, normals: ti.types.ndarray(dtype=vec3, ndim=1),
                        spacing: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    """voxel_normals.estimate, plus each point's spacing: the k nearest lie within a disc of
    radius R on the surface, so about sqrt(pi R^2 / found) apart (0 without a normal).
    Points [first, first + count): a launch stays under Vulkan's dispatch limit."""
    for i in range(first, first + count):
        nbr, found, far_d2 = k_nearest(pts, cells, i, keys, starts, ends, offsets, k, min_own)
        nrm = plane_normal(pts, nbr, found, pts[i])
        normals[i] = nrm
        spacing[i] = 0.0
        if nrm.norm_sqr() > 0.0:
            spacing[i] = ti.sqrt(3.14159265 * ti.max(far_d2, 0.0) / found)


@ti.kernel
def points_allocate_band(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1),
                         nrm: ti.types.ndarray(dtype=vec3, ndim=1),
                         steps: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32,
                         behind_m: ti.f32):
    """Allocate the blocks of each point's band patch (exactly those points_fuse_band
    visits). Idempotent: the host relaunches it while tiles were missed."""
    for i in range(n):
        allocate_patch(m, geometry(m), pts[i], nrm[i], steps[i], behind_m)


@ti.kernel
def points_fuse_band(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1),
                     nrm: ti.types.ndarray(dtype=vec3, ndim=1),
                     steps: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32,
                     sigma_weight_m: ti.f32, behind_m: ti.f32, run_length: ti.i32):
    """Each point's band: d = (v - p).n into the voxels of its patch within the truncation in
    front and behind_m behind, weighted by a Gaussian of their distance to the point.

    Points come in spatial (Morton) order, so consecutive one-column points mostly hit the
    same voxels: one thread takes run_length of them and sums their columns in registers
    (tsdf_band.column_into_slots), as scan_fuse does for a scan line; the sums are the same
    up to f32 rounding.
    """
    k_w = -0.5 / (sigma_weight_m * sigma_weight_m)
    n_max = ti.static(m.band_slots)
    for run in range((n + run_length - 1) // run_length):
        geo = geometry(m)  # once per run: the map's geometry is read at run time
        n_s = band_samples(geo, behind_m)
        slot_g = ti.Matrix.zero(ti.i32, n_max, 3)
        slot_wd = ti.Vector.zero(ti.f32, n_max)
        slot_w = ti.Vector.zero(ti.f32, n_max)
        cb = ivec3(-(1 << 30))
        bid = UNKNOWN
        for i in range(run * run_length, ti.min(n, (run + 1) * run_length)):
            point_band(m, geo, pts[i], nrm[i], steps[i], behind_m, k_w, n_s, slot_g,
                       slot_wd, slot_w, cb, bid, 1.0)
        flush_slots(m, geo, slot_g, slot_wd, slot_w)
