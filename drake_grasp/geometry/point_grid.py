"""The neighbour search of scene points around hand axes (pure numpy).

Owns the flat xy grid that buckets surface samples (`_Grid`), the query that pairs each
approach axis with the samples that can lie inside a hand outline around it
(`_neighbour_pairs`), their coordinates in the frames of all K rotated hands at once
(`_in_hand_frame`), the per-group minimum / maximum reductions the tests use, and
`_Scene`, a scene's fine and coarse samples with their grids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drake_grasp.geometry.hand_model import HAND_FOOTPRINT_RADIUS_M, STRIP_RADIUS_M
from drake_grasp.geometry.scene_samples import ScenePoints


def _group_min(values: np.ndarray, ids: np.ndarray, n: int) -> np.ndarray:
    """Per-group minimum of `values` by `ids` in [0, n); +inf for empty groups."""
    out = np.full(n, np.inf)
    # float64 values: ufunc.at is ~20x slower when it has to cast.
    np.minimum.at(out, ids, np.asarray(values, dtype=np.float64))
    return out


def _group_max(values: np.ndarray, ids: np.ndarray, n: int) -> np.ndarray:
    """Per-group maximum of `values` by `ids` in [0, n); -inf for empty groups."""
    out = np.full(n, -np.inf)
    np.maximum.at(out, ids, np.asarray(values, dtype=np.float64))
    return out



@dataclass(frozen=True)
class _Grid:
    """Points bucketed into square cells of their xy: a flat, vectorisable neighbour
    index (scipy's ball queries return Python lists, slow to flatten at ~1e6 pairs)."""

    lo: np.ndarray  # (2,) corner of cell (0, 0)
    cell: float
    shape: tuple[int, int]
    order: np.ndarray  # point indices sorted by cell
    starts: np.ndarray  # per cell: first position in `order`
    counts: np.ndarray  # per cell: number of points
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray]  # coordinates in `order`, contiguous

    @classmethod
    def build(cls, points: np.ndarray, cell: float) -> _Grid:
        xy = points[:, :2]
        lo = xy.min(axis=0) if len(xy) else np.zeros(2)
        ij = np.floor((xy - lo) / cell).astype(np.int64)
        shape = tuple(int(v) for v in (ij.max(axis=0) + 1 if len(xy) else (1, 1)))
        flat = ij[:, 0] * shape[1] + ij[:, 1]
        order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=shape[0] * shape[1])
        xyz = tuple(np.ascontiguousarray(points[order, j]) for j in range(3))
        return cls(lo, cell, shape, order, np.cumsum(counts) - counts, counts, xyz)

    def candidates(self, centers_xy: np.ndarray, radius: float):
        """(centre, sorted position) pairs of all points in the cells that a disc of
        `radius` around each centre can overlap (a superset). Grouped by centre."""
        # Never more cells than the grid has (a near-horizontal approach reaches far).
        span = int(min(np.ceil(radius / self.cell), max(self.shape)))
        off = np.arange(-span, span + 1)
        di, dj = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
        # Cells that a disc centred anywhere in cell (0, 0) can reach.
        gap_i = np.maximum(np.abs(di) - 1, 0) * self.cell
        gap_j = np.maximum(np.abs(dj) - 1, 0) * self.cell
        near = gap_i**2 + gap_j**2 <= radius**2
        di, dj = di[near], dj[near]
        ij0 = np.floor((centers_xy - self.lo) / self.cell).astype(np.int64)
        ci = ij0[:, 0, None] + di[None, :]
        cj = ij0[:, 1, None] + dj[None, :]
        ok = (ci >= 0) & (ci < self.shape[0]) & (cj >= 0) & (cj < self.shape[1])
        center = np.nonzero(ok)[0]
        cells = ci[ok] * self.shape[1] + cj[ok]
        n = self.counts[cells]
        keep = n > 0
        center, cells, n = center[keep], cells[keep], n[keep]
        total = int(n.sum())
        pos = np.repeat(self.starts[cells] - (np.cumsum(n) - n), n)
        pos += np.arange(total)
        return center, n, pos


def _neighbour_pairs(grid: _Grid, origins: np.ndarray, approach: np.ndarray, e1: np.ndarray,
                     e2: np.ndarray, radius_across: float, w_max: float):
    """(axis, point) pairs, grouped by axis, of the points that can lie in a hand
    outline of radius `radius_across` around each approach axis and no more than
    `w_max` beyond the origin along it (points further ahead cannot touch the hand).

    Culling uses distances across world z: for an axis tilted by t from vertical, the
    outline reaches at most r / cos(t) + tan(t) |dz| horizontally from the origin at
    height difference dz.

    Returns:
        axis index, point index, and the point's coordinates relative to its axis:
        u, v across it (along e1, e2) and w along the approach (all (pairs,)).
    """
    if len(origins) == 0 or len(grid.order) == 0:
        empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0)
        return empty_i, empty_i, empty_f, empty_f, empty_f
    cos_t = np.clip(-approach[:, 2], 1e-6, 1.0)
    z = grid.xyz[2]
    reach_dz = np.maximum(np.abs(z.max() - origins[:, 2]), np.abs(origins[:, 2] - z.min()))
    tan_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None)) / cos_t
    radius = radius_across / cos_t + np.where(tan_t > 1e-9, tan_t * reach_dz, 0.0) + 1e-9
    center, n, pos = grid.candidates(origins[:, :2], float(radius.max()))
    axis = np.repeat(center, n)
    dx = grid.xyz[0][pos] - np.repeat(origins[center, 0], n)
    dy = grid.xyz[1][pos] - np.repeat(origins[center, 1], n)
    dz = grid.xyz[2][pos] - np.repeat(origins[center, 2], n)
    frames = np.concatenate([approach, e1, e2], axis=1)
    if np.all(frames == frames[:1]):
        # All axes parallel with the same basis (the top-down default): scalar
        # coefficients instead of per-pair gathers.
        (ax, ay, az), (ux, uy, uz), (vx, vy, vz) = approach[0], e1[0], e2[0]
    else:
        ax, ay, az = (np.repeat(approach[center, j], n) for j in range(3))
        ux, uy, uz = (np.repeat(e1[center, j], n) for j in range(3))
        vx, vy, vz = (np.repeat(e2[center, j], n) for j in range(3))
    w = dx * ax + dy * ay + dz * az
    keep = np.flatnonzero((dx * dx + dy * dy <= np.repeat(radius[center] ** 2, n)) & (w <= w_max))
    dx, dy, dz, axis, w = dx[keep], dy[keep], dz[keep], axis[keep], w[keep]
    if not np.isscalar(ux):
        ux, uy, uz, vx, vy, vz = (c[keep] for c in (ux, uy, uz, vx, vy, vz))
    u = dx * ux + dy * uy + dz * uz
    v = dx * vx + dy * vy + dz * vz
    return axis, grid.order[pos[keep]], u, v, w


def _in_hand_frame(axis, u, v, base_angle, K, half_width, hands=None):
    """Hand-frame coordinates of the (pair, k) entries with |y_G| <= half_width.

    All K rotations of a pair are tested at once in a dense (pairs, K) block: K is
    small, and this beats generating only the runs of k that can hit (np.repeat
    with variable counts is slower than the extra arithmetic).

    Args:
        axis, u, v: per pair, from `_neighbour_pairs`.
        base_angle: (S,) angle of rotation 0 per axis; rotation k adds k pi / K.
        hands: Optional (S, K) mask: only entries of these hands are kept.

    Returns:
        x, y (entries,), hand ids g = s * K + k and pair indices (entries,).
    """
    cb, sb = np.cos(base_angle)[axis], np.sin(base_angle)[axis]
    # Coordinates at rotation 0 (float32: errors ~1e-8 m, half the memory traffic of
    # this, the largest block); rotation k then only needs a K-entry table.
    u0 = (u * cb + v * sb).astype(np.float32)
    v0 = (v * cb - u * sb).astype(np.float32)
    phase = np.pi * np.arange(K) / K
    c, s = np.cos(phase).astype(np.float32), np.sin(phase).astype(np.float32)
    Y = np.multiply.outer(v0, c)
    Y -= np.multiply.outer(u0, s)
    inside = np.abs(Y, out=Y) <= np.float32(half_width)
    if hands is not None:
        inside &= hands[axis]
    idx = np.flatnonzero(inside)
    pair = idx // K
    k = idx - pair * K
    up, vp, ck, sk = u0[pair], v0[pair], c[k], s[k]
    return up * ck + vp * sk, vp * ck - up * sk, axis[pair] * K + k, pair


@dataclass(frozen=True)
class _Scene:
    """Surface samples of a scene with their neighbour grids: a fine set for the
    closing region and contacts, a coarse one for collisions."""

    fine: ScenePoints
    coarse: ScenePoints
    fine_grid: _Grid
    coarse_grid: _Grid

    @classmethod
    def build(cls, fine: ScenePoints, coarse: ScenePoints) -> _Scene:
        # Cells of a quarter of the query radius: the cells a query disc can reach
        # hold less than twice the points of the disc itself.
        return cls(fine, coarse, _Grid.build(fine.points, STRIP_RADIUS_M / 4.0),
                   _Grid.build(coarse.points, HAND_FOOTPRINT_RADIUS_M / 4.0))
