"""Kernel compile errors still name the file, line and function after the runtime shortened
Taichi's per-statement positions (mcl3d.core.kernel_positions)."""

from pathlib import Path

import pytest


def test_a_compile_error_names_the_file_line_and_function(ti_runtime):
    import taichi as ti
    from taichi.lang.exception import TaichiNameError

    @ti.kernel
    def broken() -> ti.i32:
        return undefined_name + 1  # noqa: F821

    with pytest.raises(TaichiNameError) as error:
        broken()
    source = Path(__file__).read_text().splitlines()
    line = 1 + next(i for i, text in enumerate(source) if "return undefined_name" in text)
    message = str(error.value)
    assert f'{__file__}", line {line}, in broken' in message
    assert 'Name "undefined_name" is not defined' in message
    assert "^^^" not in message  # the short form: no source line with a caret underline
