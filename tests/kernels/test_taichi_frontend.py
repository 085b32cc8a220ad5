"""The cheaper Taichi frontend (mcl3d.kernels.taichi_frontend) answers as Taichi's own steps
do, and kernel compile errors still name the file, line and function."""

import inspect
import sys
from pathlib import Path

import pytest
from taichi.lang import kernel_impl

from mcl3d.kernels import taichi_frontend


def _taichi_inside_class(level: int) -> bool:
    """Taichi 1.7.4's own `_inside_class`, which reads the frame through inspect."""
    try:
        statement = inspect.getframeinfo(sys._getframe(level))[3][0].strip()
    except (TypeError, ValueError):  # no source there (a frozen module), too few frames
        return False
    return any(p.match(statement) for p in kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES)


def _both(level: int) -> tuple[bool, bool]:
    """(ours, Taichi's) for the statement running `level` frames above `_both`'s caller."""
    return taichi_frontend.inside_class(level + 1), _taichi_inside_class(level + 1)


def test_inside_class_answers_as_taichi_does():
    def decorated_here():  # as a decorator would ask: about the statement that called it
        return _both(2)

    class Holder:
        answers = _both(2)

    assert decorated_here() == (False, False)
    assert Holder.answers == (True, True)
    assert taichi_frontend.inside_class(10_000) is False  # past the outermost frame


def test_every_kernel_module_sees_the_same_classes_as_taichi(monkeypatch):
    import importlib.util

    seen = []

    def compare(level_of_class_stackframe):  # Taichi counts from its `_inside_class`
        seen.append(_both(level_of_class_stackframe + 1))
        return seen[-1][0]

    monkeypatch.setattr(kernel_impl, "_inside_class", compare)
    kernels = Path(taichi_frontend.__file__).parent
    paths = [p for p in sorted(kernels.glob("*.py"))
             if p.stem not in ("__init__", "taichi_frontend")]
    for path in paths:  # executed again under names of their own
        name = f"frontend_check_{path.stem}"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, name, module)
        spec.loader.exec_module(module)
    assert len(seen) > 100
    assert all(ours == theirs for ours, theirs in seen)


def test_the_source_taichi_reads_is_the_functions_source():
    def some_function(x):
        return x + 1

    lines, first = kernel_impl.getsourcelines(some_function)
    assert (lines, first) == inspect.getsourcelines(some_function)
    assert kernel_impl.getsourcelines(some_function) is kernel_impl.getsourcelines(
        some_function)  # read once
    assert kernel_impl.getsourcefile(some_function) == inspect.getsourcefile(some_function)


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
