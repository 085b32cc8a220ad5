"""Procedural worlds that reproduce the two papers' hard cases, as triangle meshes.

- office: 50 m x 20 m floor, a corridor along a row of near-identical rooms, ramps in an
  open-plan area so a ground robot's pitch and height change (the MCL paper's simulation);
- building: near-identical floors joined by a stairwell and an elevator whose cab moves
  (the SLAM paper's elevator kidnapping);
- forest: a plantation in regular rows on uneven ground (the SLAM paper's loop ambiguity);
- arena: a large, feature-poor, nearly symmetric hall (the Hilti drone-testing arena);
- warehouse: a hall of identical pallet-rack aisles with one drive-over loading ramp (MCL
  under real ambiguity with a short-range sensor; built in `warehouse.py`).

Every world also carries the routes its trajectories follow (waypoints through free space)
and the rigid jump used by the kidnap trajectory (onto a look-alike place).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import rpy_to_rot, se3
from mcl3d.sim.mesh import Mesh, MeshBuilder, merge

WORLDS = ("office", "building", "forest", "arena", "warehouse")

# Diffuse reflectivities of the materials (0..1), used for LiDAR intensity.
WALL, FLOOR, CEILING, WOOD, METAL, BARK, LEAVES, SOIL, CONCRETE = (
    0.65, 0.35, 0.7, 0.45, 0.85, 0.25, 0.4, 0.15, 0.5)


@dataclass
class Elevator:
    """A cab moving vertically in a shaft; meshes are in the cab frame (origin: floor centre)."""

    center_xy: np.ndarray
    shell: Mesh
    door: Mesh
    floor_z_m: list[float]
    door_approach_xy: np.ndarray  # a point in the corridor in front of the landing doors


@dataclass
class World:
    name: str
    seed: int
    static: Mesh  # everything that never moves
    ground: Mesh  # the surfaces a ground robot or a walker stands on
    routes: dict[str, np.ndarray]  # name -> (K, 2) xy waypoints of a closed loop
    floor_z_m: list[float]
    T_kidnap: np.ndarray  # 4x4 rigid jump onto a look-alike place
    kidnap_route: str
    elevator: Elevator | None = None
    info: dict[str, str] = field(default_factory=dict)

    def mesh_at(self, cab_z_m: float | None = None, door_closed: bool = False) -> Mesh:
        """The whole world with the elevator cab at `cab_z_m` (default: its first floor)."""
        if self.elevator is None:
            return self.static
        cab_z = self.elevator.floor_z_m[0] if cab_z_m is None else cab_z_m
        offset = np.array([*self.elevator.center_xy, cab_z])
        parts = [self.static, self.elevator.shell.translated(offset)]
        if door_closed:
            parts.append(self.elevator.door.translated(offset))
        return merge(parts)


def build_world(name: str, seed: int = 0, **size) -> World:
    """The world called `name` ('office', 'building', 'forest', 'arena', 'warehouse')."""
    from mcl3d.sim.warehouse import warehouse  # that module builds on this one's helpers

    builders = {"office": office, "building": building, "forest": forest, "arena": arena,
                "warehouse": warehouse}
    if name not in builders:
        raise ConfigError(f"unknown world {name!r}; choose one of {', '.join(WORLDS)}")
    return builders[name](seed=seed, **size)


def _slab(b: MeshBuilder, x0, x1, y0, y1, z0, z1, holes, reflectivity) -> None:
    """A horizontal slab with rectangular holes (x0, x1, y0, y1), cut into boxes."""
    xs = sorted({x0, x1, *[h[0] for h in holes], *[h[1] for h in holes]})
    ys = sorted({y0, y1, *[h[2] for h in holes], *[h[3] for h in holes]})
    for xa, xb in itertools.pairwise(xs):
        for ya, yb in itertools.pairwise(ys):
            cx, cy = 0.5 * (xa + xb), 0.5 * (ya + yb)
            if any(h[0] <= cx <= h[1] and h[2] <= cy <= h[3] for h in holes):
                continue
            b.box([xa, ya, z0], [xb, yb, z1], reflectivity)


def _wall_x(b: MeshBuilder, x0, x1, y, thick, z0, height, doors, reflectivity,
            door_h=2.1) -> None:
    """A wall along x at `y` with door openings [(xa, xb), ...] and lintels above them."""
    cuts = [x0]
    for xa, xb in sorted(doors):
        cuts += [xa, xb]
    cuts.append(x1)
    for i in range(0, len(cuts), 2):
        b.box([cuts[i], y - thick / 2, z0], [cuts[i + 1], y + thick / 2, z0 + height], reflectivity)
    for xa, xb in doors:
        b.box([xa, y - thick / 2, z0 + door_h], [xb, y + thick / 2, z0 + height], reflectivity)


def _wall_y(b: MeshBuilder, y0, y1, x, thick, z0, height, doors, reflectivity,
            door_h=2.1) -> None:
    cuts = [y0]
    for ya, yb in sorted(doors):
        cuts += [ya, yb]
    cuts.append(y1)
    for i in range(0, len(cuts), 2):
        b.box([x - thick / 2, cuts[i], z0], [x + thick / 2, cuts[i + 1], z0 + height], reflectivity)
    for ya, yb in doors:
        b.box([x - thick / 2, ya, z0 + door_h], [x + thick / 2, yb, z0 + height], reflectivity)


def _furnish_room(b: MeshBuilder, rng: np.random.Generator, x0: float, y_back: float,
                  depth: float, z0: float, width: float, facing: float) -> None:
    """Desks, a chair, a cabinet and a shelf against the back wall of a room, with a few
    centimetres of per-room jitter so rooms are near-identical but not clones.
    `facing` is +1 when the room's door is at larger y than its back wall, else -1."""
    def rect(lx0, lx1, d0, d1, h0, h1, refl):
        ya, yb = y_back + facing * d0, y_back + facing * d1
        b.box([x0 + lx0, min(ya, yb), z0 + h0], [x0 + lx1, max(ya, yb), z0 + h1], refl)

    j = lambda: rng.uniform(-0.08, 0.08)  # noqa: E731
    dx = j()
    rect(1.4 + dx, 3.4 + dx, 0.15, 0.95, 0.72, 0.76, WOOD)  # desk top
    for lx in (1.45 + dx, 3.30 + dx):
        for d in (0.2, 0.85):
            rect(lx, lx + 0.05, d, d + 0.05, 0.0, 0.72, METAL)
    c = j()
    rect(2.1 + c, 2.6 + c, 1.15, 1.6, 0.0, 0.45, METAL)  # chair seat block
    rect(2.1 + c, 2.6 + c, 1.55, 1.6, 0.45, 0.95, METAL)  # chair back
    rect(width - 1.3 + j(), width - 0.3, 0.15, 0.7, 0.0, 1.9, METAL)  # cabinet
    rect(0.25, 0.7, 2.2 + j(), depth - 3.2, 0.0, 1.6, WOOD)  # side shelf
    if rng.random() < 0.3:  # a few rooms hold an extra box: near-identical, not identical
        rect(4.0, 4.6, 1.2, 1.8, 0.0, 0.5, WOOD)


def office(seed: int = 0, n_rooms: int = 8, room_width_m: float = 6.0,
           height_m: float = 3.0) -> World:
    """Office floor: row of near-identical rooms off a corridor, open area with two ramps."""
    if n_rooms < 7:  # the kidnap jumps 4 rooms along; the ramps need the open area
        raise ConfigError(f"world.office_rooms must be >= 7, got {n_rooms}")
    rng = np.random.default_rng([seed, 1])
    b, g = MeshBuilder(), MeshBuilder()
    length = n_rooms * room_width_m + 2.0
    width = 20.0
    y_rooms, y_corr = 8.0, 10.5
    b.box([-0.2, -0.2, -0.2], [length + 0.2, width + 0.2, 0.0], FLOOR)
    g.box([-0.2, -0.2, -0.2], [length + 0.2, width + 0.2, 0.0], FLOOR)
    b.box([-0.2, -0.2, height_m], [length + 0.2, width + 0.2, height_m + 0.2], CEILING)
    for y in (0.0, width):
        _wall_x(b, -0.2, length + 0.2, y, 0.2, 0.0, height_m, [], WALL)
    for x in (0.0, length):
        _wall_y(b, 0.0, width, x, 0.2, 0.0, height_m, [], WALL)
    doors = []
    for i in range(n_rooms):
        x0 = 1.0 + i * room_width_m
        _wall_y(b, 0.0, y_rooms, x0, 0.12, 0.0, height_m, [], WALL)
        doors.append((x0 + 0.9, x0 + 2.4))
        _furnish_room(b, rng, x0, 0.0, y_rooms, 0.0, room_width_m, +1.0)
    _wall_y(b, 0.0, y_rooms, 1.0 + n_rooms * room_width_m, 0.12, 0.0, height_m, [], WALL)
    _wall_x(b, 0.0, length, y_rooms, 0.15, 0.0, height_m, doors, WALL)
    openings = [(4.0, 7.5), (length / 2 - 1.5, length / 2 + 2.0), (length - 7.5, length - 4.0)]
    _wall_x(b, 0.0, length, y_corr, 0.15, 0.0, height_m, openings, WALL, door_h=2.4)
    ramps = [(9.0, 13.0, 17.0, 21.0, 13.0, 16.0, 0.5),
             (length / 2 + 5.0, length / 2 + 8.0, length / 2 + 12.0, length / 2 + 15.0,
              13.0, 16.0, 0.6)]
    for x0, x1, x2, x3, ya, yb, h in ramps:
        for mb in (b, g):
            mb.ramp(x0, x1, ya, yb, 0.0, h, CONCRETE)
            mb.box([x1, ya, 0.0], [x2, yb, h], CONCRETE)
            mb.ramp(x2, x3, ya, yb, h, 0.0, CONCRETE)
    for px in np.arange(6.0, length - 3.0, 8.0):  # pillars and crates in the open area
        b.box([px - 0.2, 18.2, 0.0], [px + 0.2, 18.6, height_m], CONCRETE)
    for cx in np.arange(10.0, length - 3.0, 8.0) + rng.uniform(-1.0, 1.0):
        b.box([cx - 0.4, 19.2, 0.0], [cx + 0.4, 19.8, rng.uniform(0.5, 1.2)], WOOD)
    yc = 0.5 * (y_rooms + y_corr)

    def room_visit(i: int) -> list[tuple[float, float]]:
        xd = 1.0 + i * room_width_m + 1.65
        return [(xd, yc), (xd, 6.8), (xd + 1.2, 4.8), (xd + 3.0, 4.6), (xd + 2.2, 6.3),
                (xd + 0.25, 7.2), (xd + 0.25, yc)]

    ground = [(2.0, yc), *room_visit(1)]
    mid = length / 2 + 0.25
    ground += [(mid, yc), (mid, 12.2), (ramps[1][3] + 2.5, 12.5), (ramps[1][3] + 2.5, 14.5),
               (ramps[1][0] - 2.0, 14.5), (ramps[0][3] + 2.0, 14.5), (ramps[0][0] - 2.5, 14.5),
               (ramps[0][0] - 2.5, 12.0), (5.75, 12.0), (5.75, yc)]
    loop = [(2.0, yc), *room_visit(1), *room_visit(3), (length - 6.0, yc),
            (length - 5.75, 12.5), (length - 5.75, 17.0), (3.0, 17.0), (5.75, 12.0),
            (5.75, yc)]
    kidnap = [(2.0, yc), *room_visit(0), *room_visit(1), *room_visit(2), (20.5, yc)]
    survey = [(2.0, yc), *[p for i in range(n_rooms) for p in room_visit(i)], *loop[15:]]
    tours = _office_tours(room_visit, n_rooms, yc, [0.5 * (a + b) for a, b in openings],
                          lanes_y=(14.5, 17.0))  # over both ramps (y 13-16); by the pillars
    return World(
        name="office", seed=seed, static=b.build(), ground=g.build(),
        routes={"ground": np.array(ground), "loop": np.array(loop), "kidnap": np.array(kidnap),
                "handheld": np.array(loop), "survey": np.array(survey), **tours},
        floor_z_m=[0.0], T_kidnap=se3(np.eye(3), [4 * room_width_m, 0.0, 0.0]),
        kidnap_route="kidnap",
        info={"size": f"{length:.0f} x {width:.0f} m", "rooms": str(n_rooms)},
    )


PAPER_OFFICE_TOURS = 11  # the MCL paper repeated its office experiment on 11 trajectories


def _office_tours(room_visit, n_rooms: int, yc: float, openings_x: list[float],
                  lanes_y: tuple[float, float]) -> dict[str, np.ndarray]:
    """The office's `paper-office-K` routes, K = 1..11: closed tours that start where the MCL
    paper's global localization has to tell look-alike places apart (inside one of the
    near-identical rooms, eight tours; in the corridor, two; in the open area, one), visit a
    room four doors away, cross the open area (over both ramps, or along the pillars) and
    come back to the start. Fixed by the world's size alone, so every seed drives the same
    tour with its own noise."""
    def leave(i: int) -> list[tuple[float, float]]:  # from inside room i to the corridor
        return room_visit(i)[2:]

    def enter(i: int) -> list[tuple[float, float]]:  # from the corridor to the same spot
        return room_visit(i)[:2]

    def crossing(k: int, x_from: float) -> list[tuple[float, float]]:
        """Into the open area through the opening nearest `x_from`, along a lane to the
        farthest opening, back into the corridor."""
        near = min(openings_x, key=lambda x: abs(x - x_from))
        far = max(openings_x, key=lambda x: abs(x - near))
        lane = lanes_y[k % 2]
        return [(near, yc), (near, lane), (far, lane), (far, yc)]

    tours = {}
    for k in range(PAPER_OFFICE_TOURS):
        if k < 8:  # a start inside a room: rooms 0, 3, 6, 1, 4, 7, 2, 5
            start = (3 * k) % n_rooms
            other = (start + 4) % n_rooms
            tour = [*leave(start), *room_visit(other), *crossing(k, room_visit(other)[0][0]),
                    *enter(start)]
        elif k < 10:  # a start in the corridor
            x_start = openings_x[0] + (k - 7) * 0.3 * (openings_x[-1] - openings_x[0])
            other = (4 * k) % n_rooms
            tour = [(x_start, yc), *room_visit(other), *crossing(k, room_visit(other)[0][0])]
        else:  # a start in the open area, between the ramps
            mid_x = openings_x[len(openings_x) // 2]
            tour = [(mid_x, lanes_y[1]), (openings_x[0], lanes_y[1]), (openings_x[0], yc),
                    *room_visit(n_rooms // 2), (openings_x[-1], yc),
                    (openings_x[-1], lanes_y[1])]
        tours[f"paper-office-{k + 1}"] = np.array(tour)
    return tours


def _stair_flights(b: MeshBuilder, stair: tuple, z: float, floor_height_m: float) -> None:
    """Two flights of ten steps with a landing between them, from floor z to the next."""
    n_steps, rise = 10, floor_height_m / 20
    for s in range(n_steps):
        b.box([stair[0] + 0.3 * s, stair[2], z], [stair[0] + 0.3 * (s + 1), stair[2] + 1.2,
                                                  z + rise * (s + 1)], CONCRETE)
        b.box([stair[0] + 0.3 * s, stair[3] - 1.2, z + floor_height_m / 2],
              [stair[0] + 0.3 * (s + 1), stair[3], z + floor_height_m - rise * s], CONCRETE)


def _elevator_cab() -> tuple[MeshBuilder, MeshBuilder]:
    """The cab's shell (floor, roof, walls, the doorway's lintel) and its sliding door, in
    the cab's frame (floor at z = 0)."""
    shell, door = MeshBuilder(), MeshBuilder()
    half, wall, cab_h = 1.1, 0.08, 2.4
    outer = half + wall
    shell.box([-outer, -outer, -0.15], [outer, outer, 0.0], METAL)
    shell.box([-outer, -outer, cab_h], [outer, outer, cab_h + 0.1], METAL)
    shell.box([-half - wall, -half, 0.0], [-half, half, cab_h], METAL)
    shell.box([half, -half, 0.0], [half + wall, half, cab_h], METAL)
    shell.box([-half, half, 0.0], [half, half + wall, cab_h], METAL)
    shell.box([-half, -half - wall, 0.0], [-0.5, -half, cab_h], METAL)
    shell.box([0.5, -half - wall, 0.0], [half, -half, cab_h], METAL)
    shell.box([-0.5, -half - wall, 2.1], [0.5, -half, cab_h], METAL)
    door.box([-0.5, -half - wall, 0.0], [0.5, -half - 0.02, 2.1], METAL)
    return shell, door


def _room_visits(corridor_y_m: float, room_w: float) -> list[tuple[float, float]]:
    """The corridor walk into two south rooms and out again (the building's routes)."""
    loop = [(6.0, corridor_y_m)]
    for i in (2, 4):
        xd = i * room_w + 1.6
        loop += [(xd, corridor_y_m), (xd, 4.4), (xd + 1.4, 2.8), (xd + 2.8, 3.4),
                 (xd + 1.6, 4.8), (xd + 0.1, 5.3), (xd + 0.0, corridor_y_m)]
    return [*loop, (31.0, corridor_y_m), (31.0, corridor_y_m + 0.05)]


def building(seed: int = 0, n_floors: int = 3, floor_height_m: float = 3.5) -> World:
    """Near-identical floors around a corridor, a stairwell and an elevator with a moving cab."""
    if n_floors < 2:
        raise ConfigError(f"world.building_floors must be >= 2, got {n_floors}")
    rng = np.random.default_rng([seed, 2])
    b, g = MeshBuilder(), MeshBuilder()
    length, width, room_w = 40.0, 14.0, 5.0
    ys, yn = 6.0, 8.5  # corridor between the two rows of rooms
    shaft = (34.2, 36.8, 8.6, 11.4)  # elevator shaft interior
    stair = (0.2, 4.8, 8.6, 13.8)  # stairwell
    cab_xy = np.array([35.5, 10.0])
    wall_h = floor_height_m - 0.3
    floors = [k * floor_height_m for k in range(n_floors)]
    for k, z in enumerate(floors):
        holes = [] if k == 0 else [shaft, stair]
        pit = [(shaft[0], shaft[1], shaft[2], shaft[3])] if k == 0 else holes
        _slab(b, -0.2, length + 0.2, -0.2, width + 0.2, z - 0.3, z, pit, FLOOR)
        _slab(g, -0.2, length + 0.2, -0.2, width + 0.2, z - 0.3, z, pit, FLOOR)
        for y in (0.0, width):
            _wall_x(b, -0.2, length + 0.2, y, 0.2, z, wall_h, [], WALL)
        for x in (0.0, length):
            _wall_y(b, 0.0, width, x, 0.2, z, wall_h, [], WALL)
        south_doors, north_doors = [], []
        for i in range(int(length // room_w)):
            x0 = i * room_w
            if i > 0:
                _wall_y(b, 0.0, ys, x0, 0.12, z, wall_h, [], WALL)
                if not shaft[0] - 0.3 <= x0 <= shaft[1] + 0.3:
                    _wall_y(b, yn, width, x0, 0.12, z, wall_h, [], WALL)
            south_doors.append((x0 + 1.0, x0 + 2.2))
            _furnish_room(b, rng, x0, 0.0, ys, z, room_w, +1.0)
            if i == 0:
                north_doors.append((3.3, 4.7))  # stairwell entrance, beside the flights
            elif x0 + room_w <= shaft[0] - 0.2 or x0 >= shaft[1] + 0.2:
                north_doors.append((x0 + 1.0, x0 + 2.2))
                _furnish_room(b, rng, x0, width, width - yn, z, room_w, -1.0)
        north_doors.append((35.0, 36.0))  # landing doors of the elevator
        _wall_x(b, 0.0, length, ys, 0.15, z, wall_h, south_doors, WALL)
        _wall_x(b, 0.0, length, yn, 0.15, z, wall_h, north_doors, WALL)
        _wall_y(b, yn, width, shaft[0] - 0.1, 0.2, z, floor_height_m, [], CONCRETE)
        _wall_y(b, yn, width, shaft[1] + 0.1, 0.2, z, floor_height_m, [], CONCRETE)
        _wall_x(b, shaft[0] - 0.2, shaft[1] + 0.2, shaft[3] + 0.1, 0.2, z, floor_height_m, [],
                CONCRETE)
        b.box([6.0, 0.3, z + 2.5], [6.3, 0.6, z + 2.9], METAL)  # a vent: same on every floor
        if k < n_floors - 1:
            _stair_flights(b, stair, z, floor_height_m)
    top = floors[-1] + floor_height_m - 0.3
    b.box([-0.2, -0.2, top], [length + 0.2, width + 0.2, top + 0.3], CEILING)
    b.box([shaft[0], shaft[2], -1.5], [shaft[1], shaft[3], -1.3], CONCRETE)  # shaft pit
    shell, door = _elevator_cab()
    yc = 0.5 * (ys + yn)
    loop = _room_visits(yc, room_w)
    return World(
        name="building", seed=seed, static=b.build(), ground=g.build(),
        routes={"ground": np.array(loop), "loop": np.array(loop), "handheld": np.array(loop),
                "kidnap": np.array(loop)},
        floor_z_m=floors,
        T_kidnap=se3(np.eye(3), [0.0, 0.0, -floor_height_m]),
        kidnap_route="kidnap",
        elevator=Elevator(center_xy=cab_xy, shell=shell.build(), door=door.build(),
                          floor_z_m=floors, door_approach_xy=np.array([35.5, yc])),
        info={"floors": str(n_floors), "size": f"{length:.0f} x {width:.0f} m"},
    )


def forest(seed: int = 0, rows: int = 10, trees_per_row: int = 20, row_spacing_m: float = 4.0,
           tree_spacing_m: float = 3.0, border_m: float = 0.0, undergrowth: float = 0.15,
           roughness_m: float = 0.015, slope_percent: float = 0.0,
           foliage_depth_m: float = 0.0) -> World:
    """Plantation in regular rows: trunks of varied radius, conical canopies, uneven ground
    that repeats every two rows, so lanes look alike (many loop candidates). `border_m` of
    wild wood around it (trees and shrubs at random, beyond a 4 m clear headland) give a
    sensor facing out of the rows something to see; `undergrowth` is the chance of a shrub
    beside each plantation tree; `roughness_m` the ground's bumps (sigma, 1 m apart);
    `slope_percent` a hillside grade along the rows (every lane climbs and descends alike);
    `foliage_depth_m` the mean depth a laser pulse goes into a crown or shrub before a leaf
    returns it (0: foliage is a solid shell)."""
    if rows < 6 or trees_per_row < 6:  # the kidnap jumps two rows across
        raise ConfigError(f"world.forest_rows and world.forest_trees_per_row must be >= 6, "
                          f"got {rows} and {trees_per_row}")
    if border_m < 0 or not 0 <= undergrowth <= 1 or roughness_m < 0:
        raise ConfigError(f"world.forest_border_m and world.forest_roughness_m must be >= 0 "
                          f"and world.forest_undergrowth in 0..1, got {border_m:g}, "
                          f"{roughness_m:g} and {undergrowth:g}")
    if not 0 <= slope_percent <= 30 or not 0 <= foliage_depth_m <= 2:
        raise ConfigError(f"world.forest_slope_percent must be in 0..30 and "
                          f"world.forest_foliage_depth_m in 0..2, got {slope_percent:g} and "
                          f"{foliage_depth_m:g}")
    grade = slope_percent / 100.0
    rng = np.random.default_rng([seed, 3])
    b, g = MeshBuilder(), MeshBuilder()
    length = (trees_per_row + 1) * tree_spacing_m
    width = (rows + 1) * row_spacing_m
    period = 2 * row_spacing_m
    xs = np.arange(-5.0 - border_m, length + 5.0 + border_m + 1e-9, 1.0)
    ys = np.arange(-5.0 - border_m, width + 5.0 + border_m + 1e-9, 1.0)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    phase = rng.uniform(0, 2 * np.pi, 3)
    z = (0.25 * np.sin(2 * np.pi * gx / 23.0 + phase[0]) * np.cos(2 * np.pi * gy / period)
         + 0.25 * np.sin(2 * np.pi * gx / 37.0 + phase[1])
         + roughness_m * rng.standard_normal(gx.shape) + grade * gx)
    b.heightfield(xs, ys, z, SOIL)
    g.heightfield(xs, ys, z, SOIL)
    for r in range(rows):
        for c in range(trees_per_row):
            cx = (c + 1) * tree_spacing_m + rng.normal(0, 0.12)
            cy = (r + 1) * row_spacing_m + rng.normal(0, 0.12)
            radius = rng.uniform(0.08, 0.25)
            h = rng.uniform(7.0, 12.0)
            z0 = grade * cx  # the hillside under the tree (0 on flat ground)
            b.cylinder((cx, cy), radius, z0 - 0.8, z0 + h, BARK, sides=10)
            b.cone((cx, cy), rng.uniform(1.0, 1.6), z0 + 0.55 * h, z0 + h + 1.5, LEAVES,
                   sides=10, scatter_depth_m=foliage_depth_m)
            if rng.random() < undergrowth:
                sx = cx + rng.uniform(-1, 1)
                b.cone((sx, cy + rng.uniform(0.6, 1.2)), 0.5, grade * sx - 0.3, grade * sx + 0.9,
                       LEAVES, sides=6, scatter_depth_m=foliage_depth_m)
    if border_m > 0:
        _wild_wood(b, rng, (-4.0, length + 4.0, 0.0, width), border_m + 5.0, grade,
                   foliage_depth_m)
    lane = lambda r: (r + 1.5) * row_spacing_m  # noqa: E731
    x0, x1 = 1.5, length - 1.5
    loop = [(x0, lane(0)), (x1, lane(0)), (x1, lane(2)), (x0, lane(2))]
    serp = [(x0, lane(0)), (x1, lane(0)), (x1, lane(1)), (x0, lane(1)), (x0, lane(2)),
            (x1, lane(2)), (x1, lane(3)), (x0, lane(3)), (x0 - 0.01, lane(0) + 0.5)]
    routes = {"ground": np.array(loop), "loop": np.array(serp), "handheld": np.array(loop),
              "drone": np.array(serp), "kidnap": np.array(loop)}
    if rows >= PAPER_FOREST_MIN_ROWS:
        routes["paper-forest"] = _paper_forest_route(lane, length)
    return World(
        name="forest", seed=seed, static=b.build(), ground=g.build(), routes=routes,
        floor_z_m=[0.0], T_kidnap=se3(np.eye(3), [0.0, period, 0.0]), kidnap_route="kidnap",
        info={"trees": str(rows * trees_per_row), "size": f"{length:.0f} x {width:.0f} m"},
    )


WILD_TREE_SPACING_M = 2.0  # nearest distance between two trees of the wild wood
WILD_TREES_PER_M2 = 1 / 12.0  # as dense as the plantation
WILD_SHRUBS_PER_M2 = 1 / 20.0


def _wild_wood(b: MeshBuilder, rng: np.random.Generator, clear: tuple, margin_m: float,
               grade: float = 0.0, foliage_depth_m: float = 0.0) -> None:
    """Trees and shrubs at random in the band `margin_m` wide around the rectangle `clear`
    (x0, x1, y0, y1), trees no closer than WILD_TREE_SPACING_M (dart throwing), standing on
    ground that climbs `grade` along x."""
    x0, x1, y0, y1 = clear
    lo, hi = np.array([x0 - margin_m, y0 - margin_m]), np.array([x1 + margin_m, y1 + margin_m])
    area = float(np.prod(hi - lo)) - (x1 - x0) * (y1 - y0)

    def outside(p):
        return ~((p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1))

    darts = rng.uniform(lo, hi, size=(int(4 * area * WILD_TREES_PER_M2), 2))
    darts = darts[outside(darts)]
    trees: list[np.ndarray] = []
    for p in darts:
        if len(trees) >= area * WILD_TREES_PER_M2:
            break
        if not trees or np.min(np.linalg.norm(np.array(trees) - p, axis=1)) >= WILD_TREE_SPACING_M:
            trees.append(p)
    for p in trees:
        h, z0 = rng.uniform(6.0, 14.0), grade * p[0]
        b.cylinder(p, rng.uniform(0.08, 0.3), z0 - 0.8, z0 + h, BARK, sides=10)
        b.cone(p, rng.uniform(1.0, 2.2), z0 + rng.uniform(0.4, 0.7) * h, z0 + h + 1.5, LEAVES,
               sides=10, scatter_depth_m=foliage_depth_m)
    shrubs = rng.uniform(lo, hi, size=(int(area * WILD_SHRUBS_PER_M2 * 1.5), 2))
    for p in shrubs[outside(shrubs)][: int(area * WILD_SHRUBS_PER_M2)]:
        z0 = grade * p[0]
        b.cone(p, rng.uniform(0.4, 1.0), z0 - 0.3, z0 + rng.uniform(0.6, 1.6), LEAVES, sides=6,
               scatter_depth_m=foliage_depth_m)


PAPER_FOREST_MIN_ROWS = 8  # the route's serpentine climbs to lane 6 (between rows 6 and 7)
PAPER_FOREST_LANES = (1, 2, 3, 4, 5, 6, 4, 2)  # walked alternately east and west
PAPER_FOREST_LANE_OFFSET_M = 0.3  # the walker keeps north of the centre line: undergrowth
# grows on each lane's south side, up to 0.3 m from the centre line


def _paper_forest_route(lane, length_m: float) -> np.ndarray:
    """The SLAM paper's forest walk: a serpentine up lanes 1..6, back down over lanes 4 and
    2 (revisits, one against and one along the first pass's direction), then into lane 1
    where it began. Turns are on headlands 1 m beyond the rows' ends, clear of undergrowth."""
    ends = (-1.0, length_m + 1.0)
    y = lambda r: lane(r) + PAPER_FOREST_LANE_OFFSET_M  # noqa: E731
    points = []
    for k, r in enumerate(PAPER_FOREST_LANES):
        xa, xb = ends if k % 2 == 0 else ends[::-1]
        points += [(xa, y(r)), (xb, y(r))]
    points += [(ends[0], y(1)), (ends[0] + 4.0, y(1))]
    return np.array(points)


def arena(seed: int = 0, length_m: float = 40.0, width_m: float = 30.0,
          height_m: float = 10.0) -> World:
    """A large hall with symmetric columns and almost nothing else (a door, a stage and a
    crate break the symmetry)."""
    if length_m < 15 or width_m < 10:
        raise ConfigError(f"world.arena_length_m must be >= 15 and world.arena_width_m >= 10, "
                          f"got {length_m:g} and {width_m:g}")
    rng = np.random.default_rng([seed, 4])
    b, g = MeshBuilder(), MeshBuilder()
    L, W, H = length_m, width_m, height_m
    b.box([-0.3, -0.3, -0.3], [L + 0.3, W + 0.3, 0.0], CONCRETE)
    g.box([-0.3, -0.3, -0.3], [L + 0.3, W + 0.3, 0.0], CONCRETE)
    b.box([-0.3, -0.3, H], [L + 0.3, W + 0.3, H + 0.3], METAL)
    for y in (0.0, W):
        _wall_x(b, -0.3, L + 0.3, y, 0.3, 0.0, H, [], CONCRETE)
    for x in (0.0, L):
        _wall_y(b, 0.0, W, x, 0.3, 0.0, H, [], CONCRETE)
    for fx in (0.25, 0.75):
        for fy in (0.25, 0.75):
            b.box([fx * L - 0.3, fy * W - 0.3, 0.0], [fx * L + 0.3, fy * W + 0.3, H], CONCRETE)
    for fx in np.linspace(0.1, 0.9, 5):  # roof trusses, symmetric
        b.box([fx * L - 0.15, 0.0, H - 0.8], [fx * L + 0.15, W, H - 0.6], METAL)
    # What breaks the 180-degree symmetry (a hall that is exactly symmetric cannot be told
    # from its twin by any filter; real halls have doors, a stage, clutter): a roll-up door
    # panel standing 0.25 m proud of the east wall's inner face (x = L - 0.15), a low stage
    # against the west wall at a seeded place, and a crate in one corner.
    b.box([L - 0.4, 0.4 * W, 0.0], [L - 0.15, 0.4 * W + 4.0, 4.0], METAL)
    sy = rng.uniform(0.3, 0.5) * W
    b.box([0.15, sy, 0.0], [2.65, sy + 6.0, 0.8], WOOD)  # the stage
    cx = rng.uniform(2.0, 4.0)
    b.box([cx, 1.0, 0.0], [cx + 1.2, 1.8, 1.0], WOOD)  # a crate in one corner
    loop = [(5.0, 5.0), (L - 5.0, 5.0), (L - 5.0, W - 5.0), (5.0, W - 5.0)]
    drone = [(4.0, 4.0), (L - 4.0, 4.0), (L - 4.0, 0.5 * W), (0.5 * L, 0.5 * W),
             (0.5 * L, W - 4.0), (4.0, W - 4.0)]
    center = np.array([L / 2, W / 2, 0.0])
    R = rpy_to_rot(0.0, 0.0, np.pi)
    return World(
        name="arena", seed=seed, static=b.build(), ground=g.build(),
        routes={"ground": np.array(loop), "loop": np.array(loop), "handheld": np.array(loop),
                "drone": np.array(drone), "kidnap": np.array(loop)},
        floor_z_m=[0.0], T_kidnap=se3(R, center - R @ center), kidnap_route="kidnap",
        info={"size": f"{L:.0f} x {W:.0f} x {H:.0f} m"},
    )
