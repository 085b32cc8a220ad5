"""Outputs are complete or absent: atomic files, --force, output folders removed on failure."""

import os

import pytest

from mcl3d.core.errors import OutputExistsError
from mcl3d.core.outputs import atomic_open, check_writable, output_folder, write_text_atomic


def test_atomic_write_replaces_only_on_success(tmp_path):
    path = tmp_path / "traj.tum"
    write_text_atomic(path, "old\n")
    with pytest.raises(RuntimeError), atomic_open(path) as f:
        f.write("half of a new file")
        raise RuntimeError("crash while writing")
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["traj.tum"]  # no temp file left
    assert oct(path.stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_existing_output_needs_force(tmp_path):
    path = tmp_path / "map.tsdf"
    path.write_text("x")
    with pytest.raises(OutputExistsError, match="allow overwriting"):
        check_writable(path, force=False)
    check_writable(path, force=True)
    with pytest.raises(OutputExistsError, match="does not exist"):
        check_writable(tmp_path / "missing" / "map.tsdf", force=False)


def test_output_folder_is_removed_when_the_run_fails_before_writing(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(ValueError), output_folder(out):
        raise ValueError("bad input")
    assert not out.exists()
    with pytest.raises(KeyboardInterrupt), output_folder(out):
        (out / "trajectory.tum").write_text("kept\n")
        raise KeyboardInterrupt
    assert (out / "trajectory.tum").read_text() == "kept\n"
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputExistsError, match="not a folder"), output_folder(tmp_path / "file"):
        pass
