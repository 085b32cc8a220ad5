"""The batched GICP's device state as Taichi containers, each passed to the kernels of
kernels/gicp.py (and kernels/scan_grid.py) as one `ti.template()`.

A container's fields are allocated once and never replaced: Taichi compiles a kernel once
per container object, with the fields it held then (grow by making a new container).
Containers carry Taichi's `_data_oriented` mark rather than the `ti.data_oriented` decorator:
its `__getattribute__` hook costs every launch that takes a container ~10 us.
"""

from __future__ import annotations

import taichi as ti


class SourcePool:
    """Source points and their covariance rows, shared by every row of a registration.

    `points` (vec3, source frame); `cov_rows` (vec6): upper triangles (xx xy xz yy yz zz) or
    plane rows (n, α, β, 0) for αI + βnnᵀ (batch_gicp.plane_form), or None for a pool of
    points only (`has_cov_rows` False). `padding` entries past `capacity` let a block of
    lookups read beyond a row's end; `layout` SOA lets such a block load whole vectors.
    """

    _data_oriented = True  # passed to kernels as one ti.template()

    def __init__(self, capacity: int, padding: int = 0, with_cov_rows: bool = True,
                 layout: ti.Layout = ti.Layout.AOS):
        self.has_cov_rows = with_cov_rows
        self.points = ti.Vector.field(3, ti.f32, capacity + padding, layout=layout)
        self.cov_rows = ti.Vector.field(6, ti.f32, capacity + padding, layout=layout) \
            if with_cov_rows else None


class GicpRows:
    """Per row (one registration term of a pose): its pose `group`, target `map`, fixed left
    pose (`q`, `t`: the row's pose is left ∘ pose) and source point range [start, start+count)."""

    _data_oriented = True  # passed to kernels as one ti.template()

    def __init__(self, capacity: int):
        self.group = ti.field(ti.i32, capacity)
        self.map = ti.field(ti.i32, capacity)
        self.q = ti.Vector.field(4, ti.f32, capacity)
        self.t = ti.Vector.field(3, ti.f32, capacity)
        self.start = ti.field(ti.i32, capacity)
        self.count = ti.field(ti.i32, capacity)


class GicpSums:
    """Linearization sums per pose or per task: Hessian `H` (6x6, rotation first), gradient
    `b`, error `e` (½ Σ eᵀMe) and inlier count `n`."""

    _data_oriented = True  # passed to kernels as one ti.template()

    def __init__(self, capacity: int):
        self.H = ti.Matrix.field(6, 6, ti.f32, capacity)
        self.b = ti.Vector.field(6, ti.f32, capacity)
        self.e = ti.field(ti.f32, capacity)
        self.n = ti.field(ti.i32, capacity)


class GicpPoses:
    """Per pose being optimized: the accepted pose (`q_cur`, `t_cur`), the candidate
    (`q_cand`, `t_cand`), LM damping `lam`, `status` (kernels/gicp.RUNNING, ...), linearizations
    used `iters`, the sums at the candidate (`acc`) and at the accepted pose (`best`)."""

    _data_oriented = True  # passed to kernels as one ti.template()

    def __init__(self, capacity: int):
        self.q_cur = ti.Vector.field(4, ti.f32, capacity)
        self.t_cur = ti.Vector.field(3, ti.f32, capacity)
        self.q_cand = ti.Vector.field(4, ti.f32, capacity)
        self.t_cand = ti.Vector.field(3, ti.f32, capacity)
        self.lam = ti.field(ti.f32, capacity)
        self.status = ti.field(ti.i32, capacity)
        self.iters = ti.field(ti.i32, capacity)
        self.acc = GicpSums(capacity)
        self.best = GicpSums(capacity)
