"""The .tsdf map file: round trip, f16, and every kind of broken file named clearly."""

import io
import json
import zipfile

import numpy as np
import pytest

from mcl3d.core.errors import MapError, OutputExistsError


def _small_map():
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf = TsdfMap(MapGeometry(0.1, 0.3, (-1.0, -2.0, 0.5), (4, 3, 2)), 16)
    rng = np.random.default_rng(0)
    coords = np.array([[0, 0, 0], [3, 2, 1], [1, 2, 0]])
    tsdf.allocate(coords)
    sdf = rng.uniform(-0.3, 0.3, (3, 8, 8, 8)).astype(np.float32)
    weight = rng.integers(0, 5, (3, 8, 8, 8)).astype(np.float32)
    tsdf.write_blocks(coords, sdf, weight)
    tsdf.mark_free(np.array([[2, 0, 0], [0, 1, 1]]))
    return tsdf, coords, sdf, weight


def _save(tsdf, path, f16=False):
    from mcl3d.maps.map_file import save_map

    return save_map(path, tsdf, source={"kind": "test"}, build={"note": "unit test"}, f16=f16)


@pytest.mark.parametrize("f16", [False, True])
def test_round_trip(ti_runtime, tmp_path, f16):
    from mcl3d.maps.map_file import load_map, read_header

    tsdf, coords, sdf, weight = _small_map()
    path = tmp_path / "m.tsdf"
    _save(tsdf, path, f16=f16)
    header = read_header(path)
    assert header["format"] == "mcl3d-tsdf" and header["format_version"] == 2
    assert header["coarse_index"] == {"kind": "tiles", "tile_cells": 8}
    assert header["voxel_size_m"] == 0.1 and header["coarse_dims"] == [4, 3, 2]
    assert header["origin_m"] == [-1.0, -2.0, 0.5] and header["n_blocks"] == 3
    assert header["source"] == {"kind": "test"} and header["distance_dtype"] == (
        "float16" if f16 else "float32")
    loaded = load_map(path)
    assert loaded.f16 == f16 and loaded.geometry == tsdf.geometry
    data = loaded.blocks().sorted()
    order = np.lexsort(coords.T[::-1])
    np.testing.assert_array_equal(data.coords, coords[order])
    tol = 2e-4 if f16 else 0
    np.testing.assert_allclose(data.sdf, sdf[order], atol=tol)
    np.testing.assert_allclose(data.weight, weight[order], atol=tol)
    assert {tuple(c) for c in data.free_coords} == {(2, 0, 0), (0, 1, 1)}


def _as_version_1(src, dst):
    """The map as version 1 wrote it: FREE blocks as a coordinate list, no coarse index in
    the header (the members of a v1 file, written by numpy as v1 files were)."""
    from mcl3d.maps.sparse_cells import masks_to_cells

    with np.load(src) as npz:
        members = {k: npz[k] for k in npz.files}
    header = json.loads(str(members.pop("header")))
    header["format_version"] = 1
    del header["coarse_index"], header["n_free_tiles"]
    free = masks_to_cells(members.pop("free_tiles"), members.pop("free_masks"))
    with open(dst, "wb") as f:
        np.savez_compressed(f, header=np.array(json.dumps(header)), free_coords=free,
                            **members)


@pytest.mark.parametrize("f16", [False, True])
def test_version_1_files_load(ti_runtime, tmp_path, f16):
    """A version-1 file loads into the sparse index as it was saved (converted on load),
    and saving it again writes version 2 with the same blocks and free cells."""
    from mcl3d.maps.map_file import load_map, read_blocks

    tsdf, coords, sdf, weight = _small_map()
    _save(tsdf, tmp_path / "v2.tsdf", f16=f16)
    _as_version_1(tmp_path / "v2.tsdf", tmp_path / "v1.tsdf")
    header, _, data = read_blocks(tmp_path / "v1.tsdf")
    assert header["format_version"] == 1 and len(data.free_coords) == 2
    loaded = load_map(tmp_path / "v1.tsdf")
    got = loaded.blocks().sorted()
    order = np.lexsort(coords.T[::-1])
    np.testing.assert_array_equal(got.coords, coords[order])
    np.testing.assert_allclose(got.sdf, sdf[order], atol=2e-4 if f16 else 0)
    np.testing.assert_allclose(got.weight, weight[order], atol=2e-4 if f16 else 0)
    assert {tuple(c) for c in got.free_coords} == {(2, 0, 0), (0, 1, 1)}
    again = _save(loaded, tmp_path / "again.tsdf", f16=f16)
    assert again["format_version"] == 2
    with np.load(tmp_path / "v2.tsdf") as a, np.load(tmp_path / "again.tsdf") as b:
        for name in ("block_coords", "sdf", "weight", "free_tiles", "free_masks"):
            np.testing.assert_array_equal(a[name], b[name])


def test_free_cells_pack_into_tile_masks():
    """FREE cells round-trip through tiles and bit masks, in any order, across tiles."""
    from mcl3d.maps.sparse_cells import cells_to_masks, masks_to_cells

    rng = np.random.default_rng(1)
    cells = np.unique(rng.integers(0, 40, size=(500, 3)), axis=0).astype(np.int32)
    tiles, masks = cells_to_masks(cells[rng.permutation(len(cells))])
    assert masks.shape == (len(tiles), 64) and masks.dtype == np.uint8
    assert len(tiles) == len(np.unique(cells >> 3, axis=0))
    back = masks_to_cells(tiles, masks)
    np.testing.assert_array_equal(back[np.lexsort(back.T[::-1])], cells)
    one = cells_to_masks(np.array([[9, 0, 2]]))
    np.testing.assert_array_equal(one[0], [[1, 0, 0]])
    assert np.unpackbits(one[1])[(1 * 8 + 0) * 8 + 2] == 1 and one[1].sum() == 32


def test_existing_output_is_not_overwritten_without_force(ti_runtime, tmp_path):
    from mcl3d.core.outputs import check_writable

    path = tmp_path / "m.tsdf"
    path.write_text("keep me")
    with pytest.raises(OutputExistsError, match="allow overwriting"):
        check_writable(path, force=False)
    assert path.read_text() == "keep me"


def test_a_failed_save_leaves_nothing(ti_runtime, tmp_path, monkeypatch):
    tsdf, *_ = _small_map()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np.lib.format, "write_array", boom)  # mid-file: the zip is open
    with pytest.raises(OSError, match="disk full"):
        _save(tsdf, tmp_path / "m.tsdf")
    assert list(tmp_path.iterdir()) == []


def _rewrite(src, dst, change):
    """Copy a map zip, letting `change(name, array) -> array | None` edit or drop members."""
    with np.load(src) as npz:
        members = {k: npz[k] for k in npz.files}
    out = {}
    for name, arr in members.items():
        new = change(name, arr)
        if new is not None:
            out[name] = new
    with open(dst, "wb") as f:
        np.savez(f, **out)


@pytest.fixture
def saved(ti_runtime, tmp_path):
    tsdf, *_ = _small_map()
    path = tmp_path / "good.tsdf"
    _save(tsdf, path)
    return path


def test_truncated_file(saved, tmp_path):
    from mcl3d.maps.map_file import load_map

    bad = tmp_path / "cut.tsdf"
    bad.write_bytes(saved.read_bytes()[: saved.stat().st_size // 2])
    with pytest.raises(MapError, match=r"cut.tsdf.*(truncated|corrupt|not a zip)"):
        load_map(bad)


def test_corrupted_bytes_fail_the_checksum(saved, tmp_path):
    from mcl3d.maps.map_file import load_map

    with zipfile.ZipFile(saved) as z:
        info = z.getinfo("sdf.npy")
    raw = bytearray(saved.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for i in range(start + 10, start + 40):
        raw[i] ^= 0xFF
    bad = tmp_path / "flip.tsdf"
    bad.write_bytes(bytes(raw))
    with pytest.raises(MapError, match=r"flip.tsdf.*sdf.*(truncated|corrupt)"):
        load_map(bad)


def test_other_format_version(saved, tmp_path):
    from mcl3d.maps.map_file import load_map

    def change(name, arr):
        if name == "header":
            h = json.loads(str(arr))
            h["format_version"] = 99
            return np.array(json.dumps(h))
        return arr

    bad = tmp_path / "v99.tsdf"
    _rewrite(saved, bad, change)
    with pytest.raises(MapError, match=r"format version 99.*reads versions 1 and 2"):
        load_map(bad)


def test_inconsistent_sizes(saved, tmp_path):
    from mcl3d.maps.map_file import load_map

    bad = tmp_path / "sizes.tsdf"
    _rewrite(saved, bad, lambda n, a: a[:2] if n == "sdf" else a)
    with pytest.raises(MapError, match=r"'sdf' has shape .*inconsistent sizes"):
        load_map(bad)
    bad2 = tmp_path / "coords.tsdf"
    _rewrite(saved, bad2, lambda n, a: a + 10 if n == "block_coords" else a)
    with pytest.raises(MapError, match="outside the coarse grid"):
        load_map(bad2)


def test_missing_member_and_not_a_map(saved, tmp_path):
    from mcl3d.maps.map_file import load_map, read_header

    bad = tmp_path / "nofree.tsdf"
    _rewrite(saved, bad, lambda n, a: None if n == "free_masks" else a)
    with pytest.raises(MapError, match=r"lacks the member.*free_masks"):
        load_map(bad)
    text = tmp_path / "notes.tsdf"
    text.write_text("hello")
    with pytest.raises(MapError, match="not an mcl3d map"):
        read_header(text)
    with pytest.raises(MapError, match="does not exist"):
        read_header(tmp_path / "missing.tsdf")
    other = tmp_path / "other.tsdf"
    buf = io.BytesIO()
    np.savez(buf, x=np.zeros(3))
    other.write_bytes(buf.getvalue())
    with pytest.raises(MapError, match="lacks the member"):
        read_header(other)


def test_nan_values_are_rejected(saved, tmp_path):
    from mcl3d.maps.map_file import load_map

    def change(name, arr):
        if name == "weight":
            arr = arr.copy()
            arr[0, 0, 0, 0] = np.nan
        return arr

    bad = tmp_path / "nan.tsdf"
    _rewrite(saved, bad, change)
    with pytest.raises(MapError, match="'weight' contains NaN"):
        load_map(bad)
