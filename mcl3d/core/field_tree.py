"""Fields sized by the map, in a SNode tree of their own.

Taichi's offline kernel cache keys a kernel on the whole SNode tree of every field it
touches. `ti.field(shape=...)` places a field in `ti.root`, whose tree collects every field
made until the next kernel launch: a field sized by the map (a code per block, a slot per
coarse cell, a test pose per map cell) placed there next to the particle buffers made
every kernel over those buffers (sorting, resampling, statistics) compile again for each
map. Fields sized by the map go in a FieldTree instead, so only the kernels that read them
depend on the map's size.
"""

from __future__ import annotations

import taichi as ti

AXES = (ti.i, ti.ij, ti.ijk, ti.ijkl)


class FieldTree:
    """A ti.FieldsBuilder with dense placement by shape: `field`, then `finalize` once
    before the first kernel reads the fields (they live as long as the runtime, as
    `ti.root`'s do)."""

    def __init__(self):
        self._builder = ti.FieldsBuilder()

    def field(self, dtype, shape, n: int | None = None):
        """A dense field of `shape` (an int or a tuple); a vector of n when n is given."""
        shape = (shape,) if isinstance(shape, int) else tuple(int(s) for s in shape)
        f = ti.field(dtype) if n is None else ti.Vector.field(n, dtype)
        self._builder.dense(AXES[len(shape) - 1], shape).place(f)
        return f

    def finalize(self) -> None:
        self._builder.finalize()
