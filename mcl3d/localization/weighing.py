"""The sensor model on the device: scores every particle against one scan.

The map is read-only during localization, so the model is evaluated once per voxel into a
code grid (1 KiB per map block, a quarter of an f32 map); an update looks codes up in a
small log-likelihood table that depends on the sigma in use. A global search starts on a
coarse distance field of the map instead (built on the first global initialization).
With `sensor.model: paper` the grid holds the paper's eq. 3 per voxel instead (2 KiB per
block, `kernels/paper_likelihood`), rebuilt when the sigma changes.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from mcl3d.core import runtime
from mcl3d.core.field_tree import FieldTree
from mcl3d.kernels import counting_sort as ks
from mcl3d.kernels import likelihood as kl
from mcl3d.kernels import paper_likelihood as kpl
from mcl3d.localization import coarse_field
from mcl3d.localization.particle_set import ParticleSet
from mcl3d.localization.sensor_model import (
    BLOCK,
    SensorModelConfig,
    code_table,
    paper_value,
    spatial_order,
)
from mcl3d.maps.sparse_cells import tiles_of

LOCALITY_RANGE_M = 5.0  # yaw cells of the visiting order: one map cell at this range
UPLOAD_CELLS = 4 << 20  # slots or brick cells per upload launch (Vulkan: under 8M)


def coarse_layout(host: coarse_field.CoarseField) -> str:
    """How the device holds the field: the layout of fewest reads a lookup whose grid over
    the bounds takes at most likelihood.DENSE_SLOT_BYTES (as the likelihood's slot table):
    `codes`, one dense grid of codes (one read), else bricks with `slots`, a dense slot per
    block (two reads), else `tiles`, a top grid over the map's tiles of 8^3 blocks and a
    tile of slots where one holds any (three reads; memory grows with the surface only)."""
    blocks = int(np.prod(host.coarse_dims))
    if 4 * blocks * host.cells_per_block**3 <= kl.DENSE_SLOT_BYTES:
        return "codes"
    return "slots" if 4 * blocks <= kl.DENSE_SLOT_BYTES else "tiles"


class DeviceCoarseField:
    """The coarse search field (mcl3d.localization.coarse_field) on the device, as
    kernels/likelihood.coarse_code reads it, in one of the layouts of `coarse_layout`.
    Never-written slots, tiles and top entries read 0: the unknown brick."""

    _data_oriented = True  # a ti.template() argument keyed by weak reference (as TsdfMap)

    def __init__(self, host: coarse_field.CoarseField, layout: str):
        k = host.cells_per_block
        self.coarse_dims = tuple(int(d) for d in host.coarse_dims)
        self.block_shift = k.bit_length() - 1
        self.layout = layout
        tree = FieldTree()
        if layout == "codes":
            codes = codes_over_bounds(host)
            self.codes = tree.field(ti.i32, codes.shape)
            tree.finalize()
            self.codes.from_numpy(codes)
            self.nbytes = {"index": 0, "bricks": codes.nbytes}
            return
        self.bricks = tree.field(ti.i32, (len(host.bricks), k, k, k))
        coords = np.ascontiguousarray(host.block_coords, dtype=np.int32).reshape(-1, 3)
        slots = np.ascontiguousarray(host.block_slots, dtype=np.int32)
        if layout == "slots":
            self.slots = tree.field(ti.i32, self.coarse_dims)
            tree.finalize()
            index_bytes = 4 * int(np.prod(self.coarse_dims))
        else:
            tiles = tiles_of(coords)
            self.top = tree.field(ti.i32, tuple(-(-d // kl.TILE) for d in self.coarse_dims))
            self.tiles = tree.field(ti.i32, (len(tiles) + 1, kl.TILE, kl.TILE, kl.TILE))
            tree.finalize()
            index_bytes = 4 * (int(np.prod(self.top.shape)) + int(np.prod(self.tiles.shape)))
            for s in range(0, len(tiles), UPLOAD_CELLS):
                part = tiles[s:s + UPLOAD_CELLS]
                kl.write_coarse_tiles(self, part, len(part))
        for s in range(0, len(coords), UPLOAD_CELLS):
            kl.write_coarse_slots(self, coords[s:s + UPLOAD_CELLS], slots[s:s + UPLOAD_CELLS],
                                  len(coords[s:s + UPLOAD_CELLS]))
        step = max(1, UPLOAD_CELLS // k**3)
        for s in range(0, len(host.bricks), step):
            part = np.ascontiguousarray(host.bricks[s:s + step], dtype=np.int32)
            kl.write_coarse_bricks(self, s, part, len(part))
        self.nbytes = {"index": index_bytes, "bricks": 4 * host.bricks.size}


def codes_over_bounds(host: coarse_field.CoarseField) -> np.ndarray:
    """The field's codes as one grid over the bounds (X, Y, Z) int32 (for small maps)."""
    k = host.cells_per_block
    codes = np.full(np.asarray(host.coarse_dims) * k, coarse_field.COARSE_UNKNOWN, np.int32)
    local = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    at = (host.block_coords.astype(np.int64) * k)[:, None, :] + local[None]
    codes[at[..., 0], at[..., 1], at[..., 2]] = host.bricks[host.block_slots].reshape(
        len(host.block_slots), -1)
    return codes


class ScanWeigher:
    """Device fields of the sensor model, allocated once; `upload_scan` then one of
    `scan_likelihood` / `coarse_likelihood` adds a scan's log-likelihood to each particle."""

    def __init__(self, tsdf, cfg: SensorModelConfig, capacity: int):
        self.tsdf = tsdf
        self.cfg = cfg
        self.cache_block = cfg.cache_block
        if self.cache_block == "auto":
            info = runtime.current()
            self.cache_block = info is not None and info.backend != "cpu"
        self.cache_block = bool(self.cache_block)
        self._points = ti.Vector.field(3, ti.f32, shape=cfg.points)
        self._points_host = np.zeros((cfg.points, 3), np.float32)
        self._keys = ti.field(ti.i32, shape=capacity)
        self._order = ti.field(ti.i32, shape=capacity)
        self._key_starts = ti.field(ti.i32, shape=1 << (3 * kl.KEY_BITS))
        self._key_blocks = ti.field(ti.i32, shape=(1 << (3 * kl.KEY_BITS)) // ks.SCAN_BLOCK + 1)
        self._table = ti.field(ti.f32, shape=kl.N_CODES)
        self._coarse_table = ti.field(ti.f32, shape=kl.COARSE_BINS + 2)
        self._table_sigma: float | None = None
        by_map = FieldTree()  # sized by the map (field_tree)
        self._slots = by_map.field(ti.i32, kl.slot_shape(tsdf))
        if cfg.model == "paper":  # eq. 3 precomputed per voxel (set_sigma fills it)
            self._values = by_map.field(ti.f32, (tsdf.capacity + 2, kl.BLOCK, kl.BLOCK,
                                                 kl.BLOCK))
        else:
            self._codes = by_map.field(ti.i32, (tsdf.capacity + 2, kl.BLOCK, kl.BLOCK,
                                                kl.WORDS_Z))
        by_map.finalize()
        kl.build_slots(tsdf, self._slots)
        if cfg.model != "paper":
            kl.build_codes(tsdf, self._codes, tsdf.n_blocks, cfg.match_dist_m)
        self._coarse: DeviceCoarseField | None = None  # the coarse search field, once built
        self._coarse_host: coarse_field.CoarseField | None = None

    def set_sigma(self, sigma_m: float) -> bool:
        """Use the hit term with `sigma_m`; True when it changed (log-likelihoods change
        scale with sigma)."""
        if sigma_m == self._table_sigma:
            return False
        if self.cfg.model == "paper":
            kpl.build_paper_values(self.tsdf, self._values, self.tsdf.n_blocks, sigma_m,
                                   self.cfg.z_hit)
        else:
            self._table.from_numpy(code_table(self.cfg, self.tsdf.truncation_m, sigma_m))
        self._table_sigma = sigma_m
        return True

    def build_coarse(self) -> None:
        """The coarse distance field of the map, once (the first global search)."""
        if self._coarse is not None:
            return
        host = coarse_field.coarse_field(self.tsdf, self.cfg)
        self._coarse = DeviceCoarseField(host, coarse_layout(host))
        self._coarse_host = host

    @property
    def coarse_summary(self) -> dict | None:
        """The coarse search field once built: its cell, blocks with a slot, bricks and device
        bytes (slot index, bricks)."""
        if self._coarse is None:
            return None
        host = self._coarse_host
        return {"cell_m": host.cell_m, "blocks": len(host.block_coords),
                "bricks": len(host.bricks), "layout": self._coarse.layout,
                "index_bytes": self._coarse.nbytes["index"],
                "brick_bytes": self._coarse.nbytes["bricks"]}

    def upload_scan(self, pts: np.ndarray) -> None:
        """The reduced scan to the device, in Morton order of map blocks."""
        m = len(pts)
        self._points_host[:m] = pts[spatial_order(pts, self.tsdf.voxel_size_m * BLOCK)]
        self._points_host[m:] = 0.0
        self._points.from_numpy(self._points_host)

    def _sort_by_pose_cell(self, p: ParticleSet, cell_m: float) -> None:
        """Visit the particles sorted by pose cell (a point 5 m away moves about a voxel
        from one cell to the next) so that consecutive ones read the same map blocks; a
        counting sort on the device (the order within a cell does not change any result)."""
        kl.locality_keys(p.pos, p.quat, p.n, cell_m, cell_m / LOCALITY_RANGE_M, self._keys)
        ks.sort_by_key(self._keys, p.n, self._key_starts, self._key_blocks, self._order)

    def scan_likelihood(self, p: ParticleSet, n_points: int, cache_block: bool) -> None:
        """Adds the tempered log-likelihood of the uploaded scan to every log-weight."""
        self._sort_by_pose_cell(p, self.tsdf.voxel_size_m)
        if self.cfg.model == "paper":
            self._paper_likelihood(p, n_points)
            return
        kl.scan_log_likelihood(self.tsdf, self._codes, self._slots, self._order, p.pos, p.quat,
                               p.n, self._points, n_points, self._table,
                               self.cfg.tempering(n_points), p.log_w, p.match, p.ll_mean,
                               cache_block)

    def _paper_likelihood(self, p: ParticleSet, n_points: int) -> None:
        cfg, trunc = self.cfg, self.tsdf.truncation_m
        match_value = float(paper_value(cfg.match_dist_m, cfg, trunc, self._table_sigma))
        kpl.paper_scan_log_likelihood(self.tsdf, self._values, self._slots, self._order, p.pos,
                                      p.quat, p.n, self._points, n_points,
                                      cfg.z_rand / cfg.max_range_m, match_value, p.log_w, p.match,
                                      p.ll_mean)

    def coarse_likelihood(self, p: ParticleSet, n_points: int, sigma_m: float) -> None:
        """Like scan_likelihood, with the coarse search model at `sigma_m`."""
        field = self._coarse_host
        self._coarse_table.from_numpy(coarse_field.coarse_table(self.cfg, sigma_m))
        self._sort_by_pose_cell(p, field.cell_m)
        kl.coarse_scan_log_likelihood(self._coarse, ti.math.vec3(*field.origin_m),
                                      1.0 / field.cell_m, self._order, p.pos, p.quat, p.n,
                                      self._points, n_points, self._coarse_table,
                                      coarse_field.coarse_match_codes(self.cfg),
                                      self.cfg.tempering(n_points), p.log_w, p.match,
                                      p.ll_mean)
