"""A warehouse: a closed hall of identical pallet-rack aisles with one loading ramp.

The MCL ambiguity study needs a place where a short-range sensor (a 6 m range gate) sees
only look-alike views for a while: every aisle has the same rack on both sides (steel
uprights every bay, three shelf decks, pallets in the same slots of every bay, a few
centimetres of seeded jitter per load), so nothing tells the aisles apart nor the position
along an aisle better than the 2.7 m bay period. The back of each rack is closed (the wall,
or the anti-collapse mesh in the middle of a back-to-back row), so the aisles beside the
walls look like the inner ones, and the hall is 180-degree symmetric but for one thing: a
loading dock with a drive-over ramp (up 1 m, a platform, down again) in the east cross aisle,
beside the ends of aisles 2 to 4. The ramp is part of the `ground` mesh, so ground robots
drive over it.

Layout (x along the aisles, y across; aisle k's centre at y = 2.5 + 5 k m):
cross aisle 10 m | rows of `n_bays` x 2.7 m | cross aisle 10 m (dock and ramp by the wall).
"""

from __future__ import annotations

import numpy as np

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import se3
from mcl3d.sim.mesh import MeshBuilder
from mcl3d.sim.worlds import CEILING, CONCRETE, FLOOR, METAL, WALL, WOOD, World

BAY_M = 2.7  # upright to upright
RACK_DEPTH_M = 1.1  # one rack, front face to back
AISLE_WIDTH_M = 2.8
CROSS_AISLE_M = 10.0
RAMP_HEIGHT_M = 1.0
RAMP_LENGTH_M = 5.0
DOCK_LENGTH_M = 2.0
UPRIGHT_HEIGHT_M = 6.2
DECK_TOPS_M = (1.6, 3.2, 4.8)
# Loads in every bay (two pallet slots per level): (base z, goods height, on a floor pallet);
# the deck at 3.2 m stays empty, so the racks are not solid walls.
LOADS = ((0.0, 1.1, True), (1.6, 1.0, False), (4.8, 0.9, False))
PALLET_HEIGHT_M = 0.14


def _rack(b: MeshBuilder, rng: np.random.Generator, x0: float, n_bays: int, y_face: float,
          facing: float) -> None:
    """One single-depth rack along x from `x0`, front face at `y_face`; `facing` is +1 when
    its aisle lies at larger y. Loads sit in the same slots of every bay, jittered a few cm."""
    def rect(xa, xb, d0, d1, z0, z1, refl):
        ya, yb = y_face - facing * d0, y_face - facing * d1
        b.box([xa, min(ya, yb), z0], [xb, max(ya, yb), z1], refl)

    x1 = x0 + n_bays * BAY_M
    for i in range(n_bays + 1):
        xi = x0 + i * BAY_M
        rect(xi - 0.05, xi + 0.05, 0.0, 0.1, 0.0, UPRIGHT_HEIGHT_M, METAL)
        rect(xi - 0.05, xi + 0.05, 0.95, 1.05, 0.0, UPRIGHT_HEIGHT_M, METAL)
    for z in DECK_TOPS_M:  # beam and deck, continuous along the row
        rect(x0, x1, 0.0, 1.05, z - 0.12, z, METAL)
    j = lambda s: rng.uniform(-s, s)  # noqa: E731
    for i in range(n_bays):
        for slot_x in (0.7, 2.0):  # slot centres from the bay's left upright
            cx = x0 + i * BAY_M + slot_x
            for z_base, height, pallet in LOADS:
                if pallet:
                    dx = j(0.04)
                    rect(cx - 0.6 + dx, cx + 0.6 + dx, 0.02, 1.02, z_base,
                         z_base + PALLET_HEIGHT_M, WOOD)
                    z_base += PALLET_HEIGHT_M
                dx, dd = j(0.04), j(0.04)
                rect(cx - 0.55 + dx, cx + 0.55 + dx, 0.05 + dd, 1.0 + dd, z_base,
                     z_base + height + j(0.05), WOOD)


def _ramp_y(b: MeshBuilder, x0: float, x1: float, y0: float, y1: float, z_at_y0: float,
            z_at_y1: float, reflectivity: float) -> None:
    """A solid wedge whose top slopes along y from z_at_y0 to z_at_y1 (base at z=0)."""
    v = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0],
                  [x0, y0, z_at_y0], [x1, y0, z_at_y0], [x1, y1, z_at_y1], [x0, y1, z_at_y1]],
                 dtype=np.float64)
    faces = [[4, 5, 6], [4, 6, 7], [0, 2, 1], [0, 3, 2], [0, 1, 5], [0, 5, 4],
             [3, 7, 6], [3, 6, 2], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]]
    b.add(v, faces, reflectivity)


def _dock(b: MeshBuilder, g: MeshBuilder, x0: float, x_wall: float, y0: float) -> None:
    """The unique feature: ramp up along +y from (x0.., y0), a dock platform reaching the east
    wall at `x_wall`, ramp down; a rail on the platform's open side, a roll-up door behind it
    and two pallets on it."""
    x1 = x0 + 3.6
    ya, yb = y0 + RAMP_LENGTH_M, y0 + RAMP_LENGTH_M + DOCK_LENGTH_M
    for mb in (b, g):
        _ramp_y(mb, x0, x1, y0, ya, 0.0, RAMP_HEIGHT_M, CONCRETE)
        mb.box([x0, ya, 0.0], [x_wall, yb, RAMP_HEIGHT_M], CONCRETE)
        _ramp_y(mb, x0, x1, yb, yb + RAMP_LENGTH_M, RAMP_HEIGHT_M, 0.0, CONCRETE)
    h = RAMP_HEIGHT_M
    for y in (ya + 0.05, yb - 0.05):  # rail posts and top bar on the platform's west edge
        b.box([x0 + 0.02, y - 0.04, h], [x0 + 0.1, y + 0.04, h + 1.0], METAL)
    b.box([x0 + 0.02, ya, h + 0.95], [x0 + 0.1, yb, h + 1.05], METAL)
    b.box([x_wall - 0.1, ya - 0.6, h], [x_wall, yb + 0.6, h + 3.5], METAL)  # roll-up door
    for y in (ya + 0.2, ya + 1.1):
        b.box([x_wall - 1.4, y, h], [x_wall - 0.2, y + 0.8, h + PALLET_HEIGHT_M], WOOD)
        b.box([x_wall - 1.35, y + 0.05, h + PALLET_HEIGHT_M], [x_wall - 0.25, y + 0.75, h + 1.3],
              WOOD)


def warehouse(seed: int = 0, n_aisles: int = 6, n_bays: int = 13, height_m: float = 8.0
              ) -> World:
    """Hall of `n_aisles` look-alike rack aisles, rows of `n_bays` bays, one drive-over ramp."""
    if n_aisles < 6 or n_bays < 6:  # the routes use aisles 0 to 5; the ramp spans 2 to 4
        raise ConfigError(f"world.warehouse_aisles and world.warehouse_bays must be >= 6, "
                          f"got {n_aisles} and {n_bays}")
    rng = np.random.default_rng([seed, 5])
    b, g = MeshBuilder(), MeshBuilder()
    pitch = AISLE_WIDTH_M + 2 * RACK_DEPTH_M
    x0 = CROSS_AISLE_M
    x1 = x0 + n_bays * BAY_M
    L = x1 + CROSS_AISLE_M
    W = 2 * RACK_DEPTH_M + n_aisles * AISLE_WIDTH_M + (n_aisles - 1) * 2 * RACK_DEPTH_M
    H = height_m
    b.box([-0.2, -0.2, -0.2], [L + 0.2, W + 0.2, 0.0], FLOOR)
    g.box([-0.2, -0.2, -0.2], [L + 0.2, W + 0.2, 0.0], FLOOR)
    b.box([-0.2, -0.2, H], [L + 0.2, W + 0.2, H + 0.2], CEILING)
    b.box([-0.2, -0.2, 0.0], [L + 0.2, 0.0, H], WALL)
    b.box([-0.2, W, 0.0], [L + 0.2, W + 0.2, H], WALL)
    b.box([-0.2, 0.0, 0.0], [0.0, W, H], WALL)
    b.box([L, 0.0, 0.0], [L + 0.2, W, H], WALL)
    _rack(b, rng, x0, n_bays, RACK_DEPTH_M, +1.0)  # against the south wall
    _rack(b, rng, x0, n_bays, W - RACK_DEPTH_M, -1.0)  # against the north wall
    for k in range(1, n_aisles):  # back-to-back rows with a mesh panel between the racks
        yc = k * pitch
        _rack(b, rng, x0, n_bays, yc - RACK_DEPTH_M, -1.0)
        _rack(b, rng, x0, n_bays, yc + RACK_DEPTH_M, +1.0)
        b.box([x0, yc - 0.02, 0.0], [x1, yc + 0.02, UPRIGHT_HEIGHT_M], METAL)
    aisle = lambda k: RACK_DEPTH_M + AISLE_WIDTH_M / 2 + k * pitch  # noqa: E731
    _dock(b, g, x1 + 4.2, L, aisle(2) + 1.5)
    xw, xe, xr = x0 - 2.2, x1 + 2.2, x1 + 6.0  # west lane, east lane, ramp centre
    start = (x0 + 2.5, aisle(1))  # in aisle 1, heading west, away from the ramp
    # ground: aisles 1 and 2, over the ramp, aisles 5 and 0; loop: every aisle, past the
    # ramp; kidnap: aisles 1 and 2 only, so the jump two aisles north stays in free space.
    ground = [start, (xw, aisle(1)), (xw, aisle(2)), (xr, aisle(2)), (xr, aisle(5)),
              (xw, aisle(5)), (xw, aisle(0)), (xe, aisle(0)), (xe, aisle(1))]
    loop = [start, (xw, aisle(1)), (xw, aisle(2)), (xe, aisle(2)), (xe, aisle(3)),
            (xw, aisle(3)), (xw, aisle(4)), (xe, aisle(4)), (xe, aisle(5)), (xw, aisle(5)),
            (xw, aisle(0)), (xe, aisle(0)), (xe, aisle(1))]
    kidnap = [start, (xw, aisle(1)), (xw, aisle(2)), (xe, aisle(2)), (xe, aisle(1))]
    return World(
        name="warehouse", seed=seed, static=b.build(), ground=g.build(),
        routes={"ground": np.array(ground), "loop": np.array(loop), "kidnap": np.array(kidnap),
                "handheld": np.array(ground)},
        floor_z_m=[0.0], T_kidnap=se3(np.eye(3), [0.0, 2 * pitch, 0.0]), kidnap_route="kidnap",
        info={"size": f"{L:.0f} x {W:.0f} x {H:.0f} m", "aisles": str(n_aisles),
              "aisle length": f"{n_bays * BAY_M:.1f} m"},
    )
