"""Reading a two-level TSDF inside other kernels: the map container, its constants, and the
distance, weight and state of a voxel or a point (nearest, trilinear, gradient).

Every TSDF kernel takes the map `m` as `ti.template()` (mcl3d.maps.tsdf.TsdfMap), a
data-oriented container holding

- the coarse index, sparse (see `coarse_cell`): fields `tile_of` (i32 [top slots], the top
  grid flattened x-major (`top_index`): tile id + 1, 0 = no tile, -1 = the tile pool
  overflowed), `tile_flag` (i32 like `tile_of`, claimed), `tile_count` (i32 scalar),
  `tile_coord` (ivec3 [tile slots]), `cells` (i32 [tile slots, 8, 8, 8]: the coarse cell's
  value + 1, values: block id >= 0, or UNKNOWN / OVERFLOW / FREE; stored + 1 so that zeros,
  never written memory, are UNKNOWN), `cell_flag` (i32 like `cells`), `tile_misses` (i32
  scalar);
- the block pool: `sdf`, `weight` (pool [pool slots, 8, 8, 8], f32 or f16), `block_count`
  (i32 scalar), `block_coord` (ivec3 [pool slots]), `block_free` (i32 [pool slots]) and,
  when `writable`, `free_hits` (f32 pool: rays that crossed a voxel in front of their band,
  whole numbers: exact in any order) and, when `exact_sums` (a writable map but on Vulkan),
  `sum_w`, `sum_wd` (i64 pools: fixed-point sums, see below);
- where it lies, as 0-d fields read at run time: `geo_origin` (vec3: the corner of voxel
  (0, 0, 0)), `geo_dims` (ivec3: the bounds in blocks), `geo_top` (ivec3: the top grid),
  `geo_caps` (blocks, tiles that may be used); `geometry(m)` reads them into a local
  Geometry that the `*_at` functions take;
- compile-time constants, the same for every map built with the same settings:
  `voxel_size_m`, `truncation_m`, flags `writable`, `exact_sums`, `f16` and `band_slots`
  (the most band samples a point has, from the truncation in voxels). The Python
  attributes `origin_m`, `coarse_dims`, `top_dims`, `capacity`, `tile_capacity` are for
  the host (kernels that read them, e.g. the likelihood's, compile per map).

So a kernel compiles once per shape of the container's fields, not per map: a writable map
sizes its fields in powers of two (maps.tsdf.field_slots) and Taichi's offline cache, keyed
on the kernel's IR and its fields' shapes, hands maps of other sizes and origins the
kernels compiled before (Python constants would be part of the IR, and fields' shapes are).

Voxel (i, j, k) covers origin + [i, i+1) x [j, j+1) x [k, k+1) voxels; its value is the
signed distance at its centre, positive in free space, clamped to +-truncation.

While a map is being built, each voxel holds the running sums of w and of w * d / truncation
as 64-bit integers in units of 2^-32 (SUM_ONE), so that rays and points fuse with atomic
adds and no update is lost when several rays touch one voxel in the same launch. Integer
addition is associative, so the sums, and the map, do not depend on the order in which
threads add (float sums would: their rounding does); see `tsdf_band.add_fixed`. Without
`exact_sums` the pool itself holds float sums (sdf = sum of w*d, weight = sum of w).
`tsdf_fusion.finalize_blocks` turns the sums into distances and weights once. The other
TSDF modules: `tsdf_blocks` (allocation, block I/O), `tsdf_band` (a point's truncation
band), `tsdf_carve` (free space along rays), `tsdf_fusion` (the fusion kernels).
"""

import taichi as ti

BLOCK = 8
UNKNOWN = -1  # never observed
OVERFLOW = -2  # needed, but the pool was full
FREE = -3  # observed, every voxel free (no surface within truncation)
FREE_WEIGHT = 1.0  # the weight a query reports for a voxel of a FREE block
SUM_ONE = 2.0**32  # a weight of 1 in the fixed-point build sums (2^31 in all per voxel)
TILE = 8  # coarse cells per tile edge (a tile: 8^3 blocks, (3.2 m)^3 at 5 cm voxels)
TILE_SHIFT = 3
TILE_OVERFLOW = -1  # `tile_of` of a tile that did not fit in the tile pool


@ti.func
def fixed_value(total: ti.i64) -> ti.f32:
    """A fixed-point build sum as a float (the nearest f32)."""
    return ti.cast(total, ti.f32) * (1.0 / SUM_ONE)

STATE_UNKNOWN = 0
STATE_OBSERVED = 1  # observed, near or behind a surface (d < truncation)
STATE_FREE = 2  # observed, at least the truncation distance from any surface

vec2 = ti.math.vec2
vec3 = ti.math.vec3
vec4 = ti.math.vec4
ivec3 = ti.math.ivec3
BIG = 1e30  # larger than any distance or ray parameter


@ti.func
def block_capacity(m: ti.template()) -> ti.i32:
    return m.geo_caps[None][0]


@ti.func
def tile_capacity(m: ti.template()) -> ti.i32:
    return m.geo_caps[None][1]


Geometry = ti.types.struct(origin=vec3, scale=vec4, dims=ivec3, top=ivec3)


@ti.func
def geometry(m: ti.template()):
    """The map's geometry as local values (a Geometry: origin, scale = (voxel, 1 / voxel,
    truncation, 1 / truncation), coarse dims, top-grid dims). Hot loops read it once per
    ray, point or run and pass it on (the `*_at` functions): Taichi does not hoist 0-d
    field reads out of loops, and reading them per sample cost ~10 % of fusion. The scale
    stays a compile-time constant (a build setting, not the map's size; folding it keeps
    fusion as fast as before)."""
    scale = vec4(m.voxel_size_m, 1.0 / m.voxel_size_m, m.truncation_m, 1.0 / m.truncation_m)
    return Geometry(origin=m.geo_origin[None], scale=scale, dims=m.geo_dims[None],
                    top=m.geo_top[None])


@ti.func
def grid_at(geo: ti.template(), p: vec3) -> vec3:
    """Continuous voxel coordinates: voxel i spans [i, i+1)."""
    return (p - geo.origin) * geo.scale[1]


@ti.func
def center_at(geo: ti.template(), g: ivec3) -> vec3:
    return geo.origin + (ti.cast(g, ti.f32) + 0.5) * geo.scale[0]


@ti.func
def grid_holds(geo: ti.template(), g: ivec3) -> bool:
    d = geo.dims * BLOCK
    return 0 <= g[0] < d[0] and 0 <= g[1] < d[1] and 0 <= g[2] < d[2]


@ti.func
def bounds_hold(geo: ti.template(), bc: ivec3) -> bool:
    d = geo.dims
    return 0 <= bc[0] < d[0] and 0 <= bc[1] < d[1] and 0 <= bc[2] < d[2]


@ti.func
def top_slot(geo: ti.template(), tc: ivec3) -> ti.i32:
    """The flat index of top-grid cell tc (x-major)."""
    return (tc[0] * geo.top[1] + tc[1]) * geo.top[2] + tc[2]


@ti.func
def world_to_grid(m: ti.template(), p: vec3) -> vec3:
    return grid_at(geometry(m), p)


@ti.func
def top_index(m: ti.template(), tc: ivec3) -> ti.i32:
    return top_slot(geometry(m), tc)


@ti.func
def tile_entry(m: ti.template(), bc: ivec3) -> ti.i32:
    """The top grid's entry for coarse cell bc (inside the bounds): tile id + 1, 0 (none)
    or TILE_OVERFLOW."""
    return m.tile_of[top_index(m, bc >> TILE_SHIFT)]


@ti.func
def tile_id_at(m: ti.template(), geo: ti.template(), bc: ivec3) -> ti.i32:
    """The tile holding coarse cell bc (inside the bounds), -1 when it has none."""
    return m.tile_of[top_slot(geo, bc >> TILE_SHIFT)] - 1


@ti.func
def tile_id(m: ti.template(), bc: ivec3) -> ti.i32:
    return tile_id_at(m, geometry(m), bc)


@ti.func
def tile_cell(m: ti.template(), t: ti.i32, bc: ivec3) -> ti.i32:
    """Coarse cell bc's value in its tile t (block id, UNKNOWN, OVERFLOW or FREE)."""
    return m.cells[t, bc[0] & (TILE - 1), bc[1] & (TILE - 1), bc[2] & (TILE - 1)] - 1


@ti.func
def set_tile_cell(m: ti.template(), t: ti.i32, bc: ivec3, value: ti.i32):
    m.cells[t, bc[0] & (TILE - 1), bc[1] & (TILE - 1), bc[2] & (TILE - 1)] = value + 1


@ti.func
def cell_at(m: ti.template(), geo: ti.template(), bc: ivec3) -> ti.i32:
    """Coarse cell bc: its block id, or UNKNOWN (also outside the bounds and where no tile
    was allocated), OVERFLOW or FREE."""
    b = UNKNOWN
    if bounds_hold(geo, bc):
        t = tile_id_at(m, geo, bc)
        if t >= 0:
            b = tile_cell(m, t, bc)
    return b


@ti.func
def coarse_cell(m: ti.template(), bc: ivec3) -> ti.i32:
    return cell_at(m, geometry(m), bc)


@ti.func
def voxel_dw_at(m: ti.template(), geo: ti.template(), g: ivec3) -> vec2:
    """(signed distance, weight) of voxel g; unknown and outside the map give (trunc, 0)."""
    trunc = geo.scale[2]
    out = vec2(trunc, 0.0)
    if grid_holds(geo, g):
        b = cell_at(m, geo, g >> 3)
        if b >= 0:
            out = vec2(ti.cast(m.sdf[b, g[0] & 7, g[1] & 7, g[2] & 7], ti.f32),
                       ti.cast(m.weight[b, g[0] & 7, g[1] & 7, g[2] & 7], ti.f32))
        elif b == FREE:
            out = vec2(trunc, FREE_WEIGHT)
    return out


@ti.func
def voxel_dw(m: ti.template(), g: ivec3) -> vec2:
    return voxel_dw_at(m, geometry(m), g)


@ti.func
def sdf_nearest(m: ti.template(), p: vec3) -> vec2:
    """(d, w) of the voxel containing world point p (w = 0: unknown)."""
    return voxel_dw(m, ti.cast(ti.floor(world_to_grid(m, p)), ti.i32))


@ti.func
def voxel_state(m: ti.template(), g: ivec3) -> ti.i32:
    dw = voxel_dw(m, g)
    state = STATE_UNKNOWN
    if dw[1] > 0.0:
        state = STATE_OBSERVED
        if dw[0] >= m.truncation_m * 0.999:
            state = STATE_FREE
    return state


@ti.func
def state_at(m: ti.template(), p: vec3) -> ti.i32:
    return voxel_state(m, ti.cast(ti.floor(world_to_grid(m, p)), ti.i32))


@ti.func
def sdf_trilinear(m: ti.template(), p: vec3) -> vec2:
    """(d, w): d interpolated between the 8 surrounding voxel centres; w their smallest weight.

    Unknown corners count as +truncation, so w = 0 flags a value that mixes in unknowns.
    """
    geo = geometry(m)
    g = grid_at(geo, p) - 0.5
    i0 = ti.cast(ti.floor(g), ti.i32)
    f = g - ti.cast(i0, ti.f32)
    d = 0.0
    w = BIG
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        dw = voxel_dw_at(m, geo, i0 + ivec3(dx, dy, dz))
        c = ((f[0] if dx else 1.0 - f[0]) * (f[1] if dy else 1.0 - f[1])
             * (f[2] if dz else 1.0 - f[2]))
        d += c * dw[0]
        w = ti.min(w, dw[1])
    return vec2(d, w)


@ti.func
def sdf_trilinear_grad(m: ti.template(), p: vec3) -> vec4:
    """(d, dd/dx, dd/dy, dd/dz) of the trilinear interpolant at p, gradient in 1/m units."""
    geo = geometry(m)
    g = grid_at(geo, p) - 0.5
    i0 = ti.cast(ti.floor(g), ti.i32)
    f = g - ti.cast(i0, ti.f32)
    out = vec4(0.0)
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        v = voxel_dw_at(m, geo, i0 + ivec3(dx, dy, dz))[0]
        wx = f[0] if dx else 1.0 - f[0]
        wy = f[1] if dy else 1.0 - f[1]
        wz = f[2] if dz else 1.0 - f[2]
        sx = 1.0 if dx else -1.0
        sy = 1.0 if dy else -1.0
        sz = 1.0 if dz else -1.0
        out += v * vec4(wx * wy * wz, sx * wy * wz, wx * sy * wz, wx * wy * sz)
    inv = geo.scale[1]
    return vec4(out[0], out[1] * inv, out[2] * inv, out[3] * inv)
