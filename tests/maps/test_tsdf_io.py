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
    assert header["format"] == "mcl3d-tsdf" and header["format_version"] == 1
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
    with pytest.raises(MapError, match=r"format version 99.*reads version 1"):
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
    _rewrite(saved, bad, lambda n, a: None if n == "free_coords" else a)
    with pytest.raises(MapError, match=r"lacks the member.*free_coords"):
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
