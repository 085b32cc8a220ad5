"""Checks shared by the tests of commands that write a picture of their run."""

from matplotlib.image import imread

from mcl3d.evaluation.run_plots import FIGURE_SIZE_IN, PICTURE_DPI


def assert_picture(path) -> None:
    """A readable PNG of the run, at the size run_plots draws."""
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    height, width = imread(path).shape[:2]
    assert (width, height) == tuple(round(v * PICTURE_DPI) for v in FIGURE_SIZE_IN)
