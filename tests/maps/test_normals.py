"""Normals of point-cloud maps: orientation towards viewpoints and, without them, from the map."""

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from mcl3d.maps import normals as map_normals


def _plane(rng, origin, u, v, size_u, size_v, normal, spacing=0.05):
    n_pts = int(size_u * size_v / spacing**2)
    a = rng.uniform(0, size_u, n_pts)[:, None]
    b = rng.uniform(0, size_v, n_pts)[:, None]
    pts = np.asarray(origin) + a * np.asarray(u) + b * np.asarray(v)
    return pts, np.tile(np.asarray(normal, float), (n_pts, 1))


def _room(rng, size=(6.0, 4.0, 3.0)):
    """The inside of a closed room: true normals face into the room."""
    sx, sy, sz = size
    parts = [
        _plane(rng, (0, 0, 0), (1, 0, 0), (0, 1, 0), sx, sy, (0, 0, 1)),
        _plane(rng, (0, 0, sz), (1, 0, 0), (0, 1, 0), sx, sy, (0, 0, -1)),
        _plane(rng, (0, 0, 0), (1, 0, 0), (0, 0, 1), sx, sz, (0, 1, 0)),
        _plane(rng, (0, sy, 0), (1, 0, 0), (0, 0, 1), sx, sz, (0, -1, 0)),
        _plane(rng, (0, 0, 0), (0, 1, 0), (0, 0, 1), sy, sz, (1, 0, 0)),
        _plane(rng, (sx, 0, 0), (0, 1, 0), (0, 0, 1), sy, sz, (-1, 0, 0)),
    ]
    return np.vstack([p for p, _ in parts]), np.vstack([n for _, n in parts])


def _street(rng):
    """Ground, a box building (facades out, roof up) and a free-standing pole far from both."""
    x0, y0, w, d, h = 0.0, 0.0, 8.0, 6.0, 10.0
    ground, up = _plane(rng, (-10, -10, 0), (1, 0, 0), (0, 1, 0), 30, 20, (0, 0, 1), 0.15)
    seen = ~((ground[:, 0] > x0) & (ground[:, 0] < x0 + w) & (ground[:, 1] > y0)
             & (ground[:, 1] < y0 + d))  # no scan reaches the ground under the building
    parts = [(ground[seen], up[seen])]
    parts += [
        _plane(rng, (x0, y0, h), (1, 0, 0), (0, 1, 0), w, d, (0, 0, 1), 0.1),
        _plane(rng, (x0, y0, 0), (1, 0, 0), (0, 0, 1), w, h, (0, -1, 0), 0.1),
        _plane(rng, (x0, y0 + d, 0), (1, 0, 0), (0, 0, 1), w, h, (0, 1, 0), 0.1),
        _plane(rng, (x0, y0, 0), (0, 1, 0), (0, 0, 1), d, h, (-1, 0, 0), 0.1),
        _plane(rng, (x0 + w, y0, 0), (0, 1, 0), (0, 0, 1), d, h, (1, 0, 0), 0.1),
    ]
    pts, nrm = np.vstack([p for p, _ in parts]), np.vstack([n for _, n in parts])
    angle = rng.uniform(0, 2 * np.pi, 3000)
    z = rng.uniform(4.0, 7.0, 3000)  # a lamp's globe, held above the ground
    pole_n = np.c_[np.cos(angle), np.sin(angle), np.zeros(3000)]
    pole = np.c_[16 + 0.3 * pole_n[:, :2], z]
    return np.vstack([pts, pole]), np.vstack([nrm, pole_n])


def _two_rooms(rng, wall_m=0.12):
    """Two rooms side by side, one wall between them sampled on both faces."""
    a_pts, a_n = _room(rng)
    b_pts, b_n = _room(rng)
    b_pts[:, 1] += 4.0 + wall_m
    return np.vstack([a_pts, b_pts]), np.vstack([a_n, b_n])


def _agreement(oriented, truth):
    return float(np.mean(np.einsum("ij,ij->i", oriented, truth) > 0))


def _scrambled(rng, normals):
    return normals * rng.choice([-1.0, 1.0], len(normals))[:, None]


def test_a_closed_room_faces_inward_without_viewpoints():
    rng = np.random.default_rng(0)
    pts, truth = _room(rng)
    oriented = map_normals.orient_consistently(pts, _scrambled(rng, truth), cell_m=0.3)
    assert _agreement(oriented, truth) > 0.99


def test_both_faces_of_a_thin_wall_face_their_own_room():
    rng = np.random.default_rng(4)
    pts, truth = _two_rooms(rng)
    oriented = map_normals.orient_consistently(pts, _scrambled(rng, truth), cell_m=0.3)
    wall = np.abs(pts[:, 1] - 4.06) < 0.1
    assert _agreement(oriented[wall], truth[wall]) > 0.99
    assert _agreement(oriented, truth) > 0.99


def test_a_street_faces_the_open_air_and_the_pole_faces_out():
    rng = np.random.default_rng(1)
    pts, truth = _street(rng)
    oriented = map_normals.orient_consistently(pts, _scrambled(rng, truth), cell_m=0.3)
    assert _agreement(oriented, truth) > 0.99
    pole = pts[:, 2] > 3.9
    pole &= pts[:, 0] > 15
    assert _agreement(oriented[pole], truth[pole]) > 0.99


def test_estimated_normals_of_a_room_are_oriented_like_the_truth():
    rng = np.random.default_rng(2)
    pts, truth = _room(rng)
    oriented = map_normals.oriented_normals(pts, 12, None, 0.3)
    assert oriented.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(oriented, axis=1), 1.0, atol=1e-5)
    assert _agreement(oriented, truth) > 0.97  # corners' normals lean over both walls


def test_normals_face_their_nearest_viewpoint():
    rng = np.random.default_rng(3)
    pts, truth = _room(rng)
    inside = np.array([[3.0, 2.0, 1.5]])
    oriented = map_normals.oriented_normals(pts, 12, inside, 0.3)
    assert _agreement(oriented, truth) > 0.97
    outside = map_normals.orient_towards(pts, truth, np.array([[3.0, 2.0, 50.0]]))
    roof = truth[:, 2] < -0.5  # the ceiling, seen from above its roof
    assert np.all(outside[roof, 2] > 0)


def _sequential(n, i, j, cost, rel):
    """Reference: the same spanning forest walked node by node from each part's first node, a
    node taking its parent's sign times their edge's relation."""
    forest = minimum_spanning_tree(coo_matrix((cost + 1e-9, (i, j)), shape=(n, n)).tocsr())
    forest = forest + forest.T
    _, part = connected_components(forest, directed=False)
    lookup = {}
    for a, b, r in zip(i, j, rel, strict=True):
        lookup[(a, b)] = lookup[(b, a)] = r
    sign = np.zeros(n)
    for root in np.unique(part, return_index=True)[1]:
        order, pred = breadth_first_order(forest, root, directed=False, return_predecessors=True)
        sign[root] = 1.0
        for node in order[1:]:
            sign[node] = sign[pred[node]] * lookup[(node, pred[node])]
    return part, sign


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_propagated_signs_equal_a_sequential_walk(seed):
    rng = np.random.default_rng(seed)
    n = 300
    pairs = np.unique(np.sort(rng.integers(0, n, (900, 2)), axis=1), axis=0)
    i, j = pairs[pairs[:, 0] != pairs[:, 1]].T
    keep = ~((i < 60) ^ (j < 60))  # nodes 0..59 and the rest: at least two parts
    i, j = i[keep], j[keep]
    cost = rng.uniform(0, 1, len(i))
    rel = rng.choice([-1.0, 1.0], len(i))
    part, sign = map_normals._propagate(n, i, j, cost, rel)
    ref_part, ref_sign = _sequential(n, i, j, cost, rel)
    np.testing.assert_array_equal(part, ref_part)
    np.testing.assert_array_equal(sign, ref_sign)
    assert part.max() >= 1


def test_relation_across_creases():
    floor_p, floor_n = np.array([[1.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    wall_p = np.array([[0.0, 1.0, 1.0]])
    inward, outward = np.array([[1.0, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]])
    assert map_normals.relation(floor_p, floor_n, wall_p, inward)[0] == 1.0  # a room's corner
    assert map_normals.relation(floor_p, floor_n, wall_p, outward)[0] == -1.0
    roof_p, facade_p = np.array([[1.0, 1.0, 5.0]]), np.array([[0.0, 1.0, 4.0]])
    assert map_normals.relation(roof_p, floor_n, facade_p, outward)[0] == 1.0  # a building's edge
    assert map_normals.relation(roof_p, floor_n, facade_p, inward)[0] == -1.0


def test_nodes_without_edges_keep_their_sign():
    none = np.zeros(0, np.int64)
    part, sign = map_normals._propagate(3, none, none, np.zeros(0), np.zeros(0))
    np.testing.assert_array_equal(part, [0, 1, 2])
    np.testing.assert_array_equal(sign, [1.0, 1.0, 1.0])


def test_chunked_steps_give_the_same_normals(monkeypatch):
    """Edges compared and points signed a small chunk at a time (what bounds memory on a
    20 M-point map) give exactly the normals of one chunk."""
    rng = np.random.default_rng(5)
    pts, truth = _street(rng)
    scrambled = _scrambled(rng, truth)
    whole = map_normals.orient_consistently(pts, scrambled, cell_m=0.3)
    monkeypatch.setattr(map_normals, "EDGE_ROWS", 37)
    monkeypatch.setattr(map_normals, "POINT_CHUNK", 1001)
    np.testing.assert_array_equal(map_normals.orient_consistently(pts, scrambled, cell_m=0.3),
                                  whole)
