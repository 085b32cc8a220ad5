"""Surface normals of point clouds, oriented towards the free side.

With viewpoints (the sensor's positions), each normal faces its nearest viewpoint. Without them
(a map exported by another SLAM system) the orientation comes from the map itself. Hoppe et al.
(1992) propagate signs along a minimum spanning tree of the k-NN graph, edge cost
1 - |n_i . n_j|; Open3D's `orient_normals_consistent_tangent_plane` does so over every point,
did not finish a 2.6 M-point map in 8 minutes, and the same propagation over the
representatives below got only 51-61 % of the normals right on maps merged from scans: one
bad edge at a crease or across a thin wall flips everything behind it. Here:

1. one representative per `cell_m` cell and layer along the normal (the two faces of a thin
   wall share a cell, not a layer): a few per cent of the points (cells grow where that
   would exceed MAX_REPRESENTATIVES);
2. neighbours on one smooth surface compare directly; across a crease or between stacked
   surfaces, each point must lie on the same side of the other's plane (Koenig and Gumhold
   2009), trusted by how clearly it does, and not at all through a third surface;
3. signs spread along spanning trees of the smooth edges into patches, then every edge
   between two patches votes on their relation (trust-weighted), and a spanning tree of the
   patch graph by vote strength orients the patches: one bad crease edge is outvoted;
4. each connected part gets one global sign: parts with floors or ground have their lowest
   horizontal surfaces face up, compact objects (a pole, a tree) face out from their centre;
   each point then takes its representative's sign.

Boards thinner than STACKED_MIN_M seen from both sides stay ambiguous: both faces get one
sign. Measured against the world mesh in bench/bench_point_maps.py (docs/map-fusion.md).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

GRAPH_NEIGHBORS = 8  # k of the representatives' graph
HORIZONTAL_NZ = 0.9  # |n_z| above this: a floor, the ground, a ceiling or a roof
GROUND_SHARE = 0.15  # parts with at least this share of horizontal surface have a ground
LOWEST_SHARE = 0.2  # the lowest fifth of a part's horizontal surfaces are its floors
CREASE_DOT = 0.5  # neighbours' normals more than 60 degrees apart meet at a crease
STACKED_MIN_M = 0.05  # parallel neighbours this far off each other's plane: two surfaces
STACKED_SHARE = 0.7  # ... and mostly in front of or behind each other, not beside
PARALLEL_DOT = 0.9  # a surface this parallel to a crease's end may lie between its ends
MAX_REPRESENTATIVES = 1 << 20  # bounds the representatives' graph (~1 GiB at most)
POINT_CHUNK = 1 << 20  # points each point-wise step handles at once (bounds temporaries)
EDGE_ROWS = 1 << 17  # representatives whose graph edges are compared at once

Stage = Callable[[str], None]


def estimate_normals(points: np.ndarray, k: int) -> np.ndarray:
    """Unit normals (N, 3) of the k nearest neighbours' plane, with arbitrary signs."""
    import open3d as o3d  # here: 0.5 s of import that maps from logs do not need

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    return np.asarray(pcd.normals)


def orient_towards(points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray
                   ) -> np.ndarray:
    """`normals` flipped to face each point's nearest viewpoint (the sensor saw that side)."""
    _, idx = cKDTree(viewpoints).query(points, k=1, workers=-1)
    flip = np.einsum("ij,ij->i", normals, viewpoints[idx] - points) < 0
    out = normals.copy()
    out[flip] *= -1
    return out


def orient_consistently(points: np.ndarray, normals: np.ndarray, cell_m: float) -> np.ndarray:
    """`normals` with signs that agree between neighbours, floors up and objects outward."""
    rep, member = _representatives(points, _bounded_keys(points, normals, cell_m))
    rep_points, rep_normals = points[rep], normals[rep]
    edges = _Edges.of(rep_points, rep_normals)
    smooth = edges.smooth
    patch, sign = _propagate(len(rep), edges.i[smooth], edges.j[smooth],
                             1.0 - edges.weight[smooth], edges.relation[smooth])
    a, b, votes = _patch_votes(patch, sign, edges)
    parts, patch_sign = _propagate(patch.max() + 1, a, b, 1.0 / (1.0 + np.abs(votes)),
                                   np.where(votes < 0, -1.0, 1.0))
    rep_normals = rep_normals * (sign * patch_sign[patch])[:, None]
    part = parts[patch]
    rep_normals *= _part_signs(rep_points, rep_normals, part, part.max() + 1)[part, None]
    out = np.empty_like(normals)
    for s in range(0, len(points), POINT_CHUNK):  # a few (chunk, 3) temporaries at a time
        m, e = member[s:s + POINT_CHUNK], min(s + POINT_CHUNK, len(points))
        out[s:e] = normals[s:e] * relation(points[s:e], normals[s:e], rep_points[m],
                                           rep_normals[m])[:, None]
    return out


def oriented_normals(points: np.ndarray, k: int, viewpoints: np.ndarray | None, cell_m: float,
                     stage: Stage | None = None) -> np.ndarray:
    """Unit normals (N, 3) float32 facing the free side: towards the viewpoints when there are
    some, else consistently oriented over the map (see the module docstring)."""
    _say(stage, "estimate normals")
    normals = estimate_normals(points, k)
    _say(stage, "orient normals")
    if viewpoints is not None and len(viewpoints):
        normals = orient_towards(points, normals, np.asarray(viewpoints, dtype=np.float64))
    else:
        normals = orient_consistently(points, normals, cell_m)
    return normals.astype(np.float32)


def _surface_keys(points: np.ndarray, normals: np.ndarray, cell_m: float) -> np.ndarray:
    """One int64 per point naming its cell (20 bits per axis) and, within the cell, its layer
    along the normal (STACKED_MIN_M thick, 3 bits): the two faces of a thin wall share a cell
    but not a layer, so each face gets its own representative."""
    cells = np.floor((points - points.min(axis=0)) / cell_m).astype(np.int64)
    axis = np.abs(normals).argmax(axis=1)
    canonical = normals * np.sign(normals[np.arange(len(normals)), axis])[:, None]
    layer = np.floor(np.einsum("ij,ij->i", points, canonical) / STACKED_MIN_M).astype(np.int64)
    return (cells[:, 0] << 43) | (cells[:, 1] << 23) | (cells[:, 2] << 3) | (layer & 7)


def _bounded_keys(points: np.ndarray, normals: np.ndarray, cell_m: float) -> np.ndarray:
    """_surface_keys with cells of cell_m, grown while they name more than MAX_REPRESENTATIVES
    representatives (a sparse city map has about one point per 30 cm cell: its graph would
    be every point's, gigabytes): the graph's memory stays bounded, whatever the points."""
    for _ in range(4):
        keys = _surface_keys(points, normals, cell_m)
        n_reps = np.count_nonzero(np.diff(np.sort(keys))) + 1
        if n_reps <= MAX_REPRESENTATIVES:
            break
        cell_m *= 1.1 * np.sqrt(n_reps / MAX_REPRESENTATIVES)  # surfaces: cells ~ 1 / edge^2
    return keys


def _representatives(points: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per key the point nearest its members' centroid (the two faces of a wall then get
    representatives straight across from each other), and each point's key index."""
    _, member = np.unique(keys, return_inverse=True)
    count = np.bincount(member)
    centroid = np.stack([np.bincount(member, points[:, a]) for a in range(3)], 1) / count[:, None]
    spread = np.linalg.norm(points - centroid[member], axis=1)
    order = np.lexsort((spread, member))
    first = np.r_[0, np.flatnonzero(np.diff(member[order])) + 1]
    return order[first], member


def _say(stage: Stage | None, name: str) -> None:
    if stage is not None:
        stage(name)


@dataclass
class _Edges:
    """The representatives' k-NN graph: per edge its relation (+1/-1), how much to trust it
    (0..1) and whether it joins one smooth surface (a direct comparison, not a crease or
    stacked surfaces)."""

    i: np.ndarray
    j: np.ndarray
    relation: np.ndarray
    weight: np.ndarray
    smooth: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, normals: np.ndarray) -> _Edges:
        n = len(points)
        k = min(GRAPH_NEIGHBORS, n - 1)
        if k < 1:
            empty = np.zeros(0, np.int64)
            return cls(empty, empty, np.zeros(0), np.zeros(0), np.zeros(0, bool))
        _, nb = cKDTree(points).query(points, k=k + 1, workers=-1)
        parts = [cls._of_rows(points, normals, nb, s, min(s + EDGE_ROWS, n))
                 for s in range(0, n, EDGE_ROWS)]
        return cls(*(np.concatenate(field) for field in zip(*parts, strict=True)))

    @staticmethod
    def _of_rows(points, normals, nb, start: int, end: int) -> tuple:
        """The edges of representatives [start, end) (their temporaries stay that small)."""
        k = nb.shape[1] - 1
        i, j = np.repeat(np.arange(start, end), k), nb[start:end, 1:].ravel()
        c = _Comparison.of(points[i], normals[i], points[j], normals[j])
        trusted = ~(c.two_surfaces & ~c.cue)  # parallel, off each other's plane, side by side
        checked = np.flatnonzero(c.cue)
        trusted[checked] &= ~_through_a_surface(points, normals, nb, i[checked], j[checked])
        weight = np.where(c.cue, c.clearance, np.abs(c.direct)) * trusted
        return i, j, c.relation(), weight, ~c.cue & trusted


def _propagate(n: int, i: np.ndarray, j: np.ndarray, cost: np.ndarray, rel: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """(part, sign) of n nodes: connected parts of the edges (i, j), and +1/-1 per node so that
    the relations along a minimum spanning forest (edge cost `cost`) hold.

    One breadth-first walk from a hub linked to every part's first node gives each node's tree
    parent; a node's sign is the product of the relations on its path to its root, which
    pointer jumping (parent <- grandparent) multiplies in log2(depth) vectorized passes.
    """
    graph = coo_matrix((cost + 1e-9, (i, j)), shape=(n, n)).tocsr()
    forest = minimum_spanning_tree(graph)
    forest = forest + forest.T
    _, part = connected_components(forest, directed=False)
    roots = np.unique(part, return_index=True)[1]
    hub = coo_matrix((np.ones(len(roots)), (np.full(len(roots), n), roots)), shape=(n + 1, n + 1))
    linked = (_padded(forest, n + 1) + hub + hub.T).tocsr()
    order, pred = breadth_first_order(linked, n, directed=False, return_predecessors=True)
    parent = np.arange(n)
    kids = order[1:]
    parent[kids] = np.where(pred[kids] == n, kids, pred[kids])
    keys = np.r_[i * n + j, j * n + i]
    codes = np.r_[rel, rel]
    order_keys = np.argsort(keys, kind="stable")
    keys, codes = keys[order_keys], codes[order_keys]
    moved = parent != np.arange(n)
    sign = np.ones(n)
    sign[moved] = codes[np.searchsorted(keys, np.flatnonzero(moved) * n + parent[moved])]
    while True:
        grand = parent[parent]
        sign = sign * sign[parent]
        if np.array_equal(grand, parent):
            return part, sign
        parent = grand


def _through_a_surface(points, normals, nb, i, j) -> np.ndarray:
    """Whether a surface parallel to one end lies between the ends (seen among that end's
    neighbours): a floor behind a thin wall is near the wall's far face, but the wall's far
    face, not this one, meets it."""
    blocked = np.zeros(len(i), bool)
    for near, far in ((j, i), (i, j)):
        others = nb[near, 1:]
        n_near = normals[near]
        offset_far = np.einsum("ij,ij->i", points[far] - points[near], n_near)
        offset = np.einsum("ikj,ij->ik", points[others] - points[near][:, None], n_near)
        parallel = np.abs(np.einsum("ikj,ij->ik", normals[others], n_near)) > PARALLEL_DOT
        between = ((offset * offset_far[:, None] > 0) & (np.abs(offset) >= STACKED_MIN_M)
                   & (np.abs(offset) < np.abs(offset_far)[:, None]))
        blocked |= (parallel & between).any(axis=1)
    return blocked


def _patch_votes(patch: np.ndarray, sign: np.ndarray, edges: _Edges
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair of neighbouring smooth patches (a, b), the trust-weighted sum of what every
    edge between them says of their relation: one bad crease edge is outvoted by the rest."""
    pa, pb = patch[edges.i], patch[edges.j]
    cross = (pa != pb) & (edges.weight > 0)
    a, b = np.minimum(pa, pb)[cross], np.maximum(pa, pb)[cross]
    says = (edges.weight * edges.relation * sign[edges.i] * sign[edges.j])[cross]
    n_patches = patch.max() + 1
    pairs, slot = np.unique(a * n_patches + b, return_inverse=True)
    votes = np.bincount(slot, says, minlength=len(pairs))
    return pairs // n_patches, pairs % n_patches, votes


def relation(p: np.ndarray, n: np.ndarray, q: np.ndarray, m: np.ndarray) -> np.ndarray:
    """+1 where normals n (at points p) and m (at q) are oriented alike, -1 where one is flipped.

    Neighbours on one smooth surface compare directly (n . m). Across a crease (a floor
    meeting a wall, a roof meeting a facade) and between stacked parallel surfaces (the two
    faces of a thin wall, a ceiling under the next floor) the dot product misleads, but for
    consistent normals each point lies on the same side of the other's plane: in front of it
    in a concave corner or across a slot, behind it at a convex edge or inside a thin wall
    (Koenig and Gumhold 2009 use the same cue).
    """
    return _Comparison.of(p, n, q, m).relation()


@dataclass
class _Comparison:
    """Two oriented points compared (see `relation`), per pair."""

    direct: np.ndarray  # n . m
    across: np.ndarray  # ((q - p) . n) ((p - q) . m): > 0 when both lie on the same side
    clearance: np.ndarray  # how far each lies off the other's plane, over their distance
    two_surfaces: np.ndarray  # they lie at least STACKED_MIN_M off each other's plane
    cue: np.ndarray  # a crease or stacked surfaces: `across` decides, not `direct`

    @classmethod
    def of(cls, p, n, q, m) -> _Comparison:
        ahead, behind = np.einsum("ij,ij->i", q - p, n), np.einsum("ij,ij->i", p - q, m)
        off = np.minimum(np.abs(ahead), np.abs(behind))
        clearance = off / np.maximum(np.linalg.norm(q - p, axis=1), 1e-12)
        direct = np.einsum("ij,ij->i", n, m)
        two_surfaces = off >= STACKED_MIN_M
        cue = (np.abs(direct) < CREASE_DOT) | (two_surfaces & (clearance >= STACKED_SHARE))
        return cls(direct, ahead * behind, clearance, two_surfaces, cue)

    def relation(self) -> np.ndarray:
        return np.where(np.where(self.cue, self.across, self.direct) < 0, -1.0, 1.0)


def _padded(matrix, size: int):
    """`matrix` as a size x size sparse matrix (extra rows and columns empty)."""
    m = matrix.tocoo()
    return coo_matrix((m.data, (m.row, m.col)), shape=(size, size))


def _part_signs(points: np.ndarray, normals: np.ndarray, part: np.ndarray, n_parts: int
                ) -> np.ndarray:
    """+1/-1 per tree part: its lowest floors face up, or, with no floor, it faces outward."""
    sign = np.ones(n_parts)
    order = np.argsort(part, kind="stable")
    bounds = np.searchsorted(part[order], np.arange(n_parts + 1))
    for p in range(n_parts):
        idx = order[bounds[p]:bounds[p + 1]]
        nz = normals[idx, 2]
        horizontal = np.abs(nz) > HORIZONTAL_NZ
        if horizontal.mean() >= GROUND_SHARE:
            z = points[idx[horizontal], 2]
            lowest = z <= np.quantile(z, LOWEST_SHARE)
            up = np.sum(np.sign(nz[horizontal][lowest]))
        else:
            up = np.sum(np.einsum("ij,ij->i", normals[idx], points[idx] - points[idx].mean(0)))
        sign[p] = -1.0 if up < 0 else 1.0
    return sign
