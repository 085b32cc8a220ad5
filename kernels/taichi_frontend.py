"""Taichi 1.7.4's Python frontend, made cheaper for a process that launches many kernels.

Every command pays Taichi's frontend before its first kernel runs, also when the offline
cache holds the compiled code (the cache key is computed from the transformed IR):

- each `ti.func` / `ti.kernel` decoration asks `inspect.getframeinfo` whether it stands in
  a class, which resolves the frame's module by scanning `sys.modules` (0.5-3 ms each, ~280
  decorations: 0.9 s of a profiled build-map);
- each call site of a `ti.func` in a kernel fetches, re-wraps line by line and parses the
  function's source again (~870 times in build-map: 0.6 s);
- each statement formats its position with its source line wrapped at 80 columns and a
  caret underline, text only a compile error shows (0.7-0.8 s a command).

`install` answers the first from `linecache` (the same line `getframeinfo` reads), remembers
each function's source (its file does not change while the process runs) and keeps the file
and line of each statement; a compile error still names the file, line and function.
"""

from __future__ import annotations

import functools
import linecache
import sys
import textwrap
from types import SimpleNamespace

from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils


def position(context, node) -> str:
    """Where `node` of the kernel or function being transformed stands (Taichi's first line
    of its position message)."""
    line = node.lineno + context.lineno_offset
    return f'File "{context.file}", line {line}, in {context.func.func.__name__}:\n'


def inside_class(level_of_class_stackframe: int) -> bool:
    """Taichi's `_inside_class`: whether the statement `level` frames up opens a class
    (Python 3.8+) or is a `data_oriented` decorator, read from `linecache`."""
    try:
        frame = sys._getframe(level_of_class_stackframe)
        line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals)
    except ValueError:  # fewer frames than that
        return False
    statement = line.strip()
    return any(pattern.match(statement)
               for pattern in kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES)


_source_file = functools.cache(kernel_impl.getsourcefile)
_source_lines = functools.cache(kernel_impl.getsourcelines)
_wrapped_line = functools.cache(textwrap.fill)


def install() -> None:
    """Make Taichi use the cheaper frontend steps (idempotent; before kernels are defined,
    for the decorations to profit)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = position
    kernel_impl._inside_class = inside_class
    kernel_impl.getsourcefile = _source_file
    kernel_impl.getsourcelines = _source_lines
    kernel_impl.textwrap = SimpleNamespace(fill=_wrapped_line, dedent=textwrap.dedent)
