"""Shorter source positions for Taichi's kernel IR.

Taichi 1.7.4 transforms the Python source of every kernel a process launches (also when the
offline cache holds its compiled code: the cache key is computed from the transformed IR)
and, for every statement, formats where it stands: the file and line, then the source line
wrapped at 80 columns with a caret underline. Only a compile error ever shows that text,
and mcl3d's kernels compile or the tests fail. Keeping the file and line alone takes
0.7-0.8 s off every command on a 2-core cpu (a 3 s OS1-64 log: build-map 6.7 -> 5.9 s,
odometry 3.8 -> 3.1 s); an error still names the file, line and function.
"""

from __future__ import annotations

from taichi.lang.ast import ast_transformer_utils


def position(context, node) -> str:
    """Where `node` of the kernel or function being transformed stands (Taichi's first line
    of its position message)."""
    line = node.lineno + context.lineno_offset
    return f'File "{context.file}", line {line}, in {context.func.func.__name__}:\n'


def shorten() -> None:
    """Make Taichi keep `position` for each statement (once per process)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = position
