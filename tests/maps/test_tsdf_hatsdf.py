"""Import of tsdf_localization / HATSDF HDF5 maps, on a tiny file written in that layout."""

import numpy as np
import pytest

from mcl3d.core.errors import MapError

h5py = pytest.importorskip("h5py", reason="h5py is in the `h5` and `test` extras")


def _pack(value_mm, weight):
    v = value_mm.astype(np.int16).view(np.uint16).astype(np.uint32)
    w = weight.astype(np.int16).view(np.uint16).astype(np.uint32)
    return (v | (w << 16)).reshape(-1)


def _write(path, chunks):
    with h5py.File(path, "w") as f:
        group = f.create_group("map")
        for (x, y, z), (value_mm, weight) in chunks.items():
            group.create_dataset(f"{x}_{y}_{z}", data=_pack(value_mm, weight))
        group.create_dataset("0_0_0_int", data=np.zeros(4, np.int32))  # companion, ignored


def _plane_chunks():
    """A wall at global voxel x = 10 (0.64 m), observed for x < 40 in chunks (-1|0, 0, 0)."""
    idx = np.arange(64)
    chunks = {}
    for cx in (-1, 0):
        gx = cx * 64 + idx[:, None, None] + np.zeros((1, 64, 64), int)
        value = np.clip((10 - gx) * 64, -600, 600)  # positive in front of the wall (x < 10)
        weight = np.where(gx < 40, 3, 0)
        chunks[(cx, 0, 0)] = (value, weight)
    return chunks


def test_import_matches_the_written_values(ti_runtime, tmp_path):
    from mcl3d.maps.free_space import HostMap
    from mcl3d.maps.hatsdf import import_hatsdf

    path = tmp_path / "map.h5"
    chunks = _plane_chunks()
    _write(path, chunks)
    tsdf = import_hatsdf(path)
    g = tsdf.geometry
    assert g.voxel_size_m == pytest.approx(0.064) and g.truncation_m == pytest.approx(0.6)
    assert g.coarse_dims == (16, 8, 8)
    host = HostMap(tsdf)
    rng = np.random.default_rng(0)
    gv = np.stack([rng.integers(-64, 64, 500), rng.integers(0, 64, 500),
                   rng.integers(0, 64, 500)], axis=1)
    # a HATSDF grid point i sits at i * 64 mm: the centre of our voxel (i - lo)
    world_pts = gv * 0.064
    d, w = host.voxel_dw(np.floor(host.to_grid(world_pts)).astype(int))
    expected_w = np.where(gv[:, 0] < 40, 3.0, 0.0)
    expected_d = np.where(expected_w > 0, np.clip((10 - gv[:, 0]) * 0.064, -0.6, 0.6), 0.6)
    np.testing.assert_array_equal(w > 0, expected_w > 0)
    near = expected_d < 0.6
    np.testing.assert_allclose(w[near], expected_w[near])  # collapsed FREE blocks report 1
    np.testing.assert_allclose(d, expected_d, atol=1e-6)
    # blocks far in front of the wall are stored as FREE blocks, not voxel by voxel
    assert len(tsdf.blocks().free_coords) > 0


def test_bad_hdf5_files(ti_runtime, tmp_path):
    from mcl3d.maps.hatsdf import import_hatsdf

    nomap = tmp_path / "nomap.h5"
    with h5py.File(nomap, "w") as f:
        f.create_group("other")
    with pytest.raises(MapError, match="no group '/map'"):
        import_hatsdf(nomap)
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f.create_group("map").create_dataset("0_0_0", data=np.zeros(10, np.uint32))
    with pytest.raises(MapError, match="expected 64³"):
        import_hatsdf(wrong)
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(MapError, match="not a readable HDF5"):
        import_hatsdf(text)
