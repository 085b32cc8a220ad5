"""Fields sized by the map live in SNode trees of their own (mcl3d.core.field_tree): Taichi
keys a compiled kernel on the whole tree of every field it touches, so a map-sized field in
the tree of the particle buffers made every particle kernel compile again for each map
(93 kernels for a second map's `localize`, 19 now: those that read the map)."""

import numpy as np
from support.floor_map import floor_map


def tree(field) -> int:
    return field.snode.ptr.get_snode_tree_id()


def test_map_sized_fields_share_no_tree_with_particle_buffers(ti_runtime):
    from mcl3d.localization.claim_check import _Grid
    from mcl3d.localization.initialization import FreeCells
    from mcl3d.localization.particle_set import ParticleSet
    from mcl3d.localization.sensor_model import SensorModelConfig
    from mcl3d.localization.weighing import ScanWeigher

    tsdf = floor_map()
    particles = ParticleSet(64)
    weigher = ScanWeigher(tsdf, SensorModelConfig(), particles.capacity)
    weigher.build_coarse()
    corners_m = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    grid = _Grid(FreeCells(corners_m, 0.5), 0.5, 2.0, 12)
    particles.pos.fill(0.0)  # materializes the trees of the particle buffers
    by_particles = {tree(f) for f in (particles.pos, particles.log_w, weigher._keys,
                                      weigher._order, weigher._points)}
    coarse = weigher._coarse
    by_map = {name: tree(f) for name, f in [
        ("slots", weigher._slots), ("codes", weigher._codes),
        ("coarse", getattr(coarse, coarse.layout)), ("grid", grid.pos), ("best", grid.best)]}
    assert not by_particles & set(by_map.values()), by_map
    assert by_map["slots"] == by_map["codes"] and by_map["grid"] == by_map["best"]
