"""Where a detected grasp is now: planar registration of a new depth view against the
view the grasp was detected in.

A grasp detected in one view (GPD's sensor at its viewpoint) belongs to the scene as it
was then. `SceneReference` keeps that view's top-down height map around the grasp;
`register` finds the planar motion of the scene, a turn `yaw_deg` about the grasp's
anchor and a translation `xy_m`, that best explains a new view's points (world frame,
back-projected at the pose the controller believes). A shifted sheet under the objects
and a hand that is not where the controller believes (kinematic noise) look the same to
a wrist camera, and both are corrected by moving the grasp with that motion
(`moved_pose`).

The search is exhaustive over a yaw grid and, per yaw, over every translation in the
search window at once (masked sum of squared height differences, computed with FFT
cross-correlations), refined below a cell by parabolas through the best cell and its
neighbours. Floor: geometry only (numpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HeightMap:
    """Top-down height map: `heights[i, j]` is the highest point in the cell whose centre
    is `origin_xy + cell_m * (i, j)` (i along world x, j along world y); `known` marks
    cells that hold a point."""

    origin_xy: np.ndarray
    cell_m: float
    heights: np.ndarray
    known: np.ndarray


def height_map(P_W: np.ndarray, centre_xy, half_m: float, cell_m: float) -> HeightMap:
    """The height map of points `P_W` ((3 or 4, N) world points) in the square of half
    side `half_m` around `centre_xy`, cells of `cell_m`."""
    n = max(1, int(round(2.0 * half_m / cell_m)))
    corner = np.asarray(centre_xy, float)[:2] - 0.5 * n * cell_m
    ij = np.floor((np.asarray(P_W, float)[:2].T - corner) / cell_m).astype(int)
    inside = np.all((ij >= 0) & (ij < n), axis=1)
    heights = np.full((n, n), -np.inf)
    np.maximum.at(heights, (ij[inside, 0], ij[inside, 1]), np.asarray(P_W, float)[2, inside])
    known = np.isfinite(heights)
    heights[~known] = 0.0
    return HeightMap(corner + 0.5 * cell_m, float(cell_m), heights, known)


@dataclass(frozen=True)
class Motion:
    """The scene's planar motion since the reference view: a point r of the scene then is
    at R(yaw) (r - anchor) + anchor + xy now (xy in the world's x, y [m]). `rms_m`: the
    root of the best match's score (its height mismatch, a cell the reference did not see
    counted as `miss_m`); `overlap`: its share of the new view's cells that the reference
    also saw."""

    xy_m: tuple = (0.0, 0.0)
    yaw_deg: float = 0.0
    rms_m: float = 0.0
    overlap: float = 1.0

    def apply(self, anchor_xy, p_xy) -> np.ndarray:
        """Where the point(s) `p_xy` ((2,) or (N, 2)) of the reference scene are now."""
        a = np.asarray(anchor_xy, float)[:2]
        c, s = np.cos(np.deg2rad(self.yaw_deg)), np.sin(np.deg2rad(self.yaw_deg))
        R = np.array([[c, -s], [s, c]])
        return (np.asarray(p_xy, float) - a) @ R.T + a + np.asarray(self.xy_m)


def moved_pose(X_WG: np.ndarray, anchor_xy, motion: Motion) -> np.ndarray:
    """A pose (4x4) of the reference scene moved with the scene: turned `motion.yaw_deg`
    about the world vertical through the anchor, then translated (its height and tilt
    kept)."""
    X = np.array(X_WG, dtype=float)
    c, s = np.cos(np.deg2rad(motion.yaw_deg)), np.sin(np.deg2rad(motion.yaw_deg))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.eye(4)
    out[:3, :3] = Rz @ X[:3, :3]
    out[:2, 3] = motion.apply(anchor_xy, X[:2, 3])
    out[2, 3] = X[2, 3]
    return out


def _correlate(template_fft: np.ndarray, image_fft: np.ndarray, shape) -> np.ndarray:
    """sum_p T[p] I[p + u] for every shift u, from the (zero-padded) FFTs."""
    return np.fft.irfft2(np.conj(template_fft) * image_fft, s=shape)


def _parabola_offset(lo: float, mid: float, hi: float) -> float:
    """The minimum's offset (in steps, within +-0.5) of a parabola through three values."""
    den = lo - 2.0 * mid + hi
    if not np.isfinite(den) or den <= 0.0:
        return 0.0
    return float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5))


def compose(outer: Motion, inner: Motion, rms_m: float, overlap: float) -> Motion:
    """`outer` after `inner` (both about the same anchor)."""
    c, s = np.cos(np.deg2rad(outer.yaw_deg)), np.sin(np.deg2rad(outer.yaw_deg))
    xy = np.asarray(outer.xy_m) + np.array([[c, -s], [s, c]]) @ np.asarray(inner.xy_m)
    return Motion(xy_m=(float(xy[0]), float(xy[1])), yaw_deg=outer.yaw_deg + inner.yaw_deg,
                  rms_m=rms_m, overlap=overlap)


class _Grid:
    """One search: the reference's height map at one cell size and translation window."""

    def __init__(self, P_W: np.ndarray, anchor: np.ndarray, template_half_m: float,
                 search_m: float, cell_m: float, miss_m: float, lag_m: float):
        self.anchor, self.template_half_m, self.cell_m = anchor, template_half_m, cell_m
        self.miss_m, self.lag_m = miss_m, lag_m
        ref = height_map(P_W, anchor, template_half_m + search_m, cell_m)
        self._n_ref = ref.heights.shape[0]
        self._n_tpl = max(1, int(round(2.0 * template_half_m / cell_m)))
        self._zero = (self._n_ref - self._n_tpl) // 2  # the shift index of no motion
        size = int(2 ** np.ceil(np.log2(self._n_ref)))
        self._shape = (size, size)
        k, h = ref.known.astype(float), ref.heights
        self._ref_fft = [np.fft.rfft2(a, s=self._shape) for a in (k, k * h, k * h * h)]
        self.known_fraction = float(ref.known.mean())

    def search(self, P: np.ndarray, yaws: np.ndarray, prior: Motion,
               min_overlap: float) -> Motion | None:
        """The best motion over `yaws` and every translation of the window."""
        a, valid = self.anchor, self._n_ref - self._n_tpl + 1
        u = (np.arange(valid) - self._zero) * self.cell_m
        best, per_yaw = None, []
        for yaw in yaws:
            c, s = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))
            R = np.array([[c, -s], [s, c]])
            # The new view taken back by the turn (translations are found below).
            q = (P[:2].T - a) @ R + a
            tpl = height_map(np.vstack([q.T, P[2]]), a, self.template_half_m, self.cell_m)
            kt = tpl.known.astype(float)
            cells = kt.sum()
            if cells == 0:
                per_yaw.append(np.inf)
                continue
            ht = tpl.heights
            t_fft = [np.fft.rfft2(x, s=self._shape) for x in (kt, kt * ht, kt * ht * ht)]
            overlap = _correlate(t_fft[0], self._ref_fft[0], self._shape)[:valid, :valid]
            ssd = (_correlate(t_fft[2], self._ref_fft[0], self._shape)
                   - 2.0 * _correlate(t_fft[1], self._ref_fft[1], self._shape)
                   + _correlate(t_fft[0], self._ref_fft[2], self._shape))[:valid, :valid]
            # The mean height difference is taken out: a camera that lags behind its
            # commanded height sees the whole scene higher or lower, not elsewhere.
            diff = (_correlate(t_fft[1], self._ref_fft[0], self._shape)
                    - _correlate(t_fft[0], self._ref_fft[1], self._shape))[:valid, :valid]
            ok = overlap >= max(1.0, min_overlap * cells)
            n = np.maximum(overlap, 1.0)
            # Per cell of the new view: the squared mismatch where the reference saw it,
            # `miss_m`**2 where it did not (a match that overlaps little is not a good
            # one), and the part of the mean difference beyond `lag_m` (a lag explains a
            # few centimetres; a flat patch matched to another flat patch far below it is
            # not one).
            offset = diff / n
            beyond = np.maximum(np.abs(offset) - self.lag_m, 0.0)
            score = np.where(ok, (np.maximum(ssd - diff * offset, 0.0)
                                  + (cells - overlap) * self.miss_m ** 2) / cells
                             + beyond ** 2, np.inf)
            # Ties (a featureless window): the motion nearest the prior.
            moved = -np.stack(np.meshgrid(u, u, indexing="ij"), -1) @ R.T
            tie = np.linalg.norm(moved - np.asarray(prior.xy_m), axis=-1) + 1e-3 * abs(
                yaw - prior.yaw_deg)
            score = score + 1e-9 * tie
            i, j = np.unravel_index(np.argmin(score), score.shape)
            per_yaw.append(score[i, j])
            if np.isfinite(score[i, j]) and (best is None or score[i, j] < best[0]):
                best = (score[i, j], len(per_yaw) - 1, i, j, score, overlap[i, j] / cells, R)
        if best is None:
            return None
        value, k, i, j, score, overlap, R = best

        def around(f, m, n):
            return [f(m + d) if 0 <= m + d < n else np.inf for d in (-1, 0, 1)]

        di = _parabola_offset(*around(lambda m: score[m, j], i, valid))
        dj = _parabola_offset(*around(lambda m: score[i, m], j, valid))
        step = float(yaws[1] - yaws[0]) if len(yaws) > 1 else 0.0
        dyaw = _parabola_offset(*around(lambda m: per_yaw[m], k, len(per_yaw)))
        shift = np.array([(i + di - self._zero) * self.cell_m, (j + dj - self._zero) * self.cell_m])
        xy = -(R @ shift)
        return Motion(xy_m=(float(xy[0]), float(xy[1])), yaw_deg=float(yaws[k] + dyaw * step),
                      rms_m=float(np.sqrt(max(value, 0.0))), overlap=float(overlap))


class SceneReference:
    """The reference view's height maps around a grasp's anchor, ready to register new
    views against (`register`): a coarse search over the whole window, then a fine one
    around its result."""

    def __init__(self, P_W: np.ndarray, anchor_xy, *, template_half_m: float,
                 search_m: float, cell_m: float, miss_m: float = 0.02, lag_m: float = 0.03):
        """Args:
            P_W: the reference view's world points ((3 or 4, N)).
            anchor_xy: the grasp's position on the table (x, y) [m]; turns are about it.
            template_half_m: half side of the square of a new view matched [m].
            search_m: the largest translation searched, per axis [m].
            cell_m: the fine search's cell [m] (the coarse search's is twice that).
            miss_m: what a cell of the new view that the reference did not see costs, as a
                height mismatch [m].
            lag_m: the mean height difference taken out at no cost [m]; beyond it, it
                counts as mismatch.
        """
        self.anchor = np.asarray(anchor_xy, float)[:2].copy()
        P = np.asarray(P_W, float)[:3]
        self._coarse = _Grid(P, self.anchor, template_half_m, search_m, 2.0 * cell_m,
                             miss_m, lag_m)
        self._fine = _Grid(P, self.anchor, template_half_m, 3.0 * cell_m, cell_m, miss_m, lag_m)
        self.known_fraction = self._fine.known_fraction

    def register(self, P_W: np.ndarray, *, prior: Motion, yaw_range_deg: float,
                 yaw_step_deg: float, min_overlap: float = 0.3) -> Motion | None:
        """The scene's motion that best explains the new view `P_W` ((3 or 4, N) world
        points): every translation within the search window (not only near `prior`'s),
        turns within `yaw_range_deg` of none (not of `prior`'s: an elongated object, whose
        turn its image hardly shows, would let a window that follows the estimate wander
        off by whole turns) on a `yaw_step_deg` grid, then refined within one coarse step,
        to a fifth of it. Ties go to the motion nearest `prior`. None when no candidate
        overlaps the reference in `min_overlap` of the new view's cells."""
        P = np.asarray(P_W, float)[:3]
        yaws = np.arange(-yaw_range_deg, yaw_range_deg + 1e-9, yaw_step_deg)
        coarse = self._coarse.search(P, yaws, prior, min_overlap)
        if coarse is None:
            return None
        # The view taken back by the coarse motion, then matched finely around no motion.
        a = self.anchor
        c, s = np.cos(np.deg2rad(coarse.yaw_deg)), np.sin(np.deg2rad(coarse.yaw_deg))
        R = np.array([[c, -s], [s, c]])
        back = (P[:2].T - a - np.asarray(coarse.xy_m)) @ R + a
        fine_yaws = np.linspace(-yaw_step_deg, yaw_step_deg, 11)
        fine = self._fine.search(np.vstack([back.T, P[2]]), fine_yaws, Motion(), min_overlap)
        if fine is None:
            return coarse
        return compose(coarse, fine, fine.rms_m, fine.overlap)
