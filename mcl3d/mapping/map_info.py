"""`mcl3d map-info`: what a map file holds (its header, blocks, voxels and memory), and the
optional exports of its surface for viewers.

`MapInfo.as_dict()` gives the same facts for scripts (`mcl3d map-info --json`), under the keys
documented in docs/json-output.md (schema `mcl3d.map_info/1`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d.core.outputs import check_writable
from mcl3d.mapping.pipeline import MapExports
from mcl3d.maps import export
from mcl3d.maps.map_file import read_blocks
from mcl3d.maps.tsdf import MapGeometry, MapStats, block_stats, loaded_bytes_per_block

SCHEMA = "mcl3d.map_info/1"  # bump the number when a key changes meaning or goes away


@dataclass(frozen=True)
class MapInfo:
    path: Path
    header: dict  # the file's header, as build-map wrote it
    geometry: MapGeometry
    stats: MapStats  # memory as loaded for localization
    exports: MapExports
    mesh_path: Path | None = None
    points_path: Path | None = None

    def as_dict(self) -> dict:
        """The facts of the table as plain JSON types (docs/json-output.md)."""
        g, h = self.geometry, self.header
        lo, hi = self.stats.extent_lo_m, self.stats.extent_hi_m
        return {
            "schema": SCHEMA, "path": str(self.path), "format": h["format"],
            "format_version": h["format_version"], "mcl3d_version": h.get("mcl3d_version"),
            "created_utc": h.get("created_utc"), "frame_id": h["frame_id"],
            "precision": h["distance_dtype"], "voxel_size_m": g.voxel_size_m,
            "truncation_m": g.truncation_m, "origin_m": list(g.origin_m),
            "block_size_m": round(g.block_size_m, 9), "coarse_dims": list(g.coarse_dims),
            "extent_lo_m": lo, "extent_hi_m": hi,
            "extent_size_m": [round(b - a, 3) for a, b in zip(lo, hi, strict=True)],
            "source": h.get("source"), "build": h.get("build"),
            **self.stats.as_dict(),
            "exports": {
                "mesh": None if self.mesh_path is None else {
                    "path": str(self.mesh_path), "triangles": self.exports.mesh_triangles},
                "points": None if self.points_path is None else {
                    "path": str(self.points_path), "points": self.exports.surface_points}},
        }


def map_info(path: Path, *, export_mesh: Path | None = None, export_points: Path | None = None,
             force: bool = False) -> MapInfo:
    """Read a map file, count its blocks and voxels, and write the exports asked for (each
    checked writable before the map is read)."""
    path = Path(path)
    for out in (export_mesh, export_points):
        if out:
            check_writable(out, force)
    header, geometry, data = read_blocks(path)
    stats = block_stats(geometry, data, loaded_bytes_per_block(data.sdf.dtype == np.float16))
    stats = dataclasses.replace(stats, file_bytes=path.stat().st_size)
    exports = MapExports(
        mesh_triangles=export.write_mesh(export_mesh, geometry, data) if export_mesh else None,
        surface_points=(export.write_points(export_points, geometry, data)
                        if export_points else None))
    return MapInfo(path, header, geometry, stats, exports, export_mesh, export_points)
