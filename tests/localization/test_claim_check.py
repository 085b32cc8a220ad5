"""The convergence check (mcl3d.localization.claim_check): a claim stands only when no other
place explains the scans about as well, even a place where the filter holds no particles."""

import itertools

import numpy as np
import pytest

from mcl3d.core import geometry

localize_world = pytest.importorskip("support.localize_world")
N_PARTICLES = 3000


@pytest.fixture(scope="module")
def two_rooms(backend):
    """Two identical closed rooms side by side (the second 10.4 m along x) and a scanner in
    the first: every scan fits both rooms equally."""
    from mcl3d.core import runtime

    runtime.init(backend)
    room = localize_world.build_map(0.1)
    offset_blocks = int(room.coarse_dims[0]) + 2
    tsdf = localize_world.placed_together([(room, (0, 0, 0)), (room, (offset_blocks, 0, 0))],
                                          0.1)
    shift_m = offset_blocks * 8 * 0.1
    return tsdf, localize_world.Scanner(n_azimuth=180, seed=5), shift_m


def run_search(tsdf, scanner, check: bool, n_scans: int = 24, withhold_all: bool = False):
    """A global search whose particles all start in the first room (the second room's died,
    as they do with too few particles for the map); the results per scan. `withhold_all`:
    the localizer withholds every claim without checking (the search, and the check's window
    of scans, go on to the last scan)."""
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    path = localize_world.path(n_scans)
    rng = np.random.default_rng(7)
    positions = path[0][:3, 3] + rng.normal(0.0, [0.1, 0.1, 0.02], (N_PARTICLES, 3))
    yaw = geometry.rot_to_rpy(path[0][:3, :3])[2] + rng.normal(0.0, 0.03, N_PARTICLES)
    quats = geometry.rot_to_quat(geometry.so3_exp(np.column_stack([0 * yaw, 0 * yaw, yaw])))
    cfg = LocalizerConfig.model_validate({
        "particles": N_PARTICLES, "seed": 4, "recovery": {"enabled": False},
        "init": {"height_band_m": [0.5, 1.1]}, "check": {"enabled": check}})
    loc = Localizer(tsdf, cfg, imu_roll_pitch=(0.0, 0.0))
    if withhold_all:
        loc._claim_withheld = lambda T_claim: True
    loc.init_particles(positions, quats, search=True)
    steps = itertools.chain([None], (geometry.relative_se3(a, b)
                                     for a, b in itertools.pairwise(path)))
    results = [loc.step(scanner.scan(T), dT, 0.1 * k)
               for k, (T, dT) in enumerate(zip(path, steps, strict=True))]
    return loc, results, path


def test_without_the_check_the_filter_claims_one_of_two_identical_rooms(two_rooms, ti_runtime):
    tsdf, scanner, _ = two_rooms
    loc, results, _ = run_search(tsdf, scanner, check=False)
    assert any(r.state == "converged" for r in results)
    assert loc.claim_check.runs == 0


def test_the_check_withholds_the_claim_while_both_rooms_explain_the_scans(two_rooms,
                                                                            ti_runtime):
    tsdf, scanner, shift_m = two_rooms
    loc, results, path = run_search(tsdf, scanner, check=True)
    assert all(r.state != "converged" for r in results)
    assert loc.claim_check.withheld >= 1 and loc.claim_check.reseeded_particles > 0
    # the second room got particles at the true pose shifted by one room, and keeps them
    pos, _, _ = loc.particles.host()
    twin = path[-1][:3, 3] + [shift_m, 0.0, 0.0]
    near_twin = np.linalg.norm(pos - twin, axis=1) < 0.5
    assert near_twin.sum() >= loc.cfg.resample.place_min_particles
    assert results[-1].state == "ambiguous"
    d = np.linalg.norm(results[-1].T_map_lidar[:3, 3] - path[-1][:3, 3])
    assert min(d, abs(d - shift_m)) < 0.2  # the estimate is one of the two rooms


def test_the_check_finds_a_place_whose_pose_now_has_no_global_candidate(two_rooms, ti_runtime):
    """The twin room's pose now lies in a hole of the candidates (a doorway: the map saw no
    floor there); the grid placed at the newest scan cannot reach it, the grid placed at an
    earlier scan of the window (1.7 m back) can."""
    from mcl3d.localization.claim_check import ClaimCheck
    from mcl3d.localization.initialization import FreeCells

    tsdf, scanner, shift_m = two_rooms
    loc, results, path = run_search(tsdf, scanner, check=True, n_scans=40, withhold_all=True)
    assert len(loc.claim_check.window.scans) == len(path)
    free = loc.free_space()
    twin_now = path[-1][:3, 3] + [shift_m, 0.0, 0.0]
    centres = free.corners_m + 0.5 * free.cell_m
    hole = np.linalg.norm(centres[:, :2] - twin_now[:2], axis=1) < 1.0
    holed = FreeCells(free.corners_m[~hole], free.cell_m)
    T_claim = results[-1].T_map_lidar
    found = {}
    for anchors in (1, 2):
        cfg = loc.cfg.model_copy(update={"check": loc.cfg.check.model_copy(
            update={"anchor_scans": anchors, "window_scans": 4})})
        check = ClaimCheck(cfg)
        check.window = loc.claim_check.window
        rivals = check.rivals(loc.weigher, loc.particles, T_claim, holed, 4, 1)
        found[anchors] = [np.linalg.norm(r.T_map_lidar[:3, 3] - twin_now) for r in rivals]
    assert not any(d < 0.4 for d in found[1])
    assert any(d < 0.4 for d in found[2])
