"""The geometric detector's hand candidates and their geometric tests (stages 3 and 4).

From the object points of one depth image (`object_points`: the cloud above the table
with contact normals, pixel footprints and connected objects) the detector draws sample
points with the caller's RNG (`sample_neighbourhoods`), orients each sample's first
closing direction along the horizontal surface normal or a flat top's minor axis
(`first_closing_directions`), sweeps `num_rotations` top-down hands about it straight
down over the neighbouring points (`sweep_hands`: the highest point under the pads,
the fingers, the palm and the housing), places them at the requested depths below the
local top and keeps those that collide with no visible point's column
(`collision_free_heights`), then demands enough points between the pads, one object and
an antipodal pair of contact patches (`closing_contacts`). The survivors' yaws and
centres come from `survivor_poses`. Vectorised over hands x neighbouring points; pure
numpy / scipy, the same operations and order as one pass (see `gpd_geometric`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from drake_grasp.geometry.contact_physics import force_closure
from drake_grasp.geometry.hand_model import (FINGER_OUTER_X_M, FINGERTIP_Z_M,
                                             HAND_FOOTPRINT_RADIUS_M, HOUSING_FRONT_Z_M,
                                             HOUSING_RADIUS_M, PAD_HALF_LENGTH_M, PAD_HALF_WIDTH_M,
                                             PALM_FRONT_Z_M, PALM_HALF_X_M, PALM_HALF_Y_M, STROKE_M)
from drake_grasp.policies.gpd_geometric_cloud import OrganizedCloud, _contact_normals

HALF_STROKE_M = 0.5 * STROKE_M
# Below this horizontal component a normal gives no closing direction (flat tops):
# sin(12 deg), as `grasps.sample_grasp_candidates`.
_MIN_HORIZONTAL_NORMAL = 0.2
# Radius of the footprint whose minor axis orients hands on flat tops [m].
_FOOTPRINT_RADIUS_M = 0.03
# Per-depth results of `closing_contacts`, concatenated over the depths.
CONTACT_KEYS = ("axis", "d", "count", "xmin", "xmax", "c0", "c1", "n0", "n1", "label", "area")


@dataclass(frozen=True)
class ObjectPoints:
    """Per-point attributes of the cloud above the table (M points), and its objects.

    Attributes:
        P: (M, 3) world points [m].
        Nc: (M, 3) contact normals (`gpd_geometric_cloud._contact_normals`).
        is_wall: (M,) silhouette points (a hidden wall goes down from them).
        label: (M,) connected object of each point (8-connected in the image).
        area: (M,) area each point stands for, across the optical axis [m^2].
        px_all: (M,) a pixel's footprint at each point [m].
        px_wall: (M,) that footprint at silhouette points, else 0 [m].
        half_px: (M,) half of `px_wall` [m].
        cx_l, cy_l, rad_l: per object label, the centroid's x, y and the largest xy
            distance of its points from it [m].
    """

    P: np.ndarray
    Nc: np.ndarray
    is_wall: np.ndarray
    label: np.ndarray
    area: np.ndarray
    px_all: np.ndarray
    px_wall: np.ndarray
    half_px: np.ndarray
    cx_l: np.ndarray
    cy_l: np.ndarray
    rad_l: np.ndarray


@dataclass(frozen=True)
class Neighbourhoods:
    """The S sample points and, per sample, the object points near its hand axis.

    Pairs (sample, point) within the hand's footprint radius, sorted by sample
    (contiguous runs per sample, each starting at `starts`).

    Attributes:
        S: Number of samples.
        samples: (S,) indices of the sampled points, sorted.
        C: (S, 3) the sampled points (the hand axes pass through them) [m].
        s_idx, p_idx: (pairs,) sample and point index of each pair.
        pdx, pdy, pr2: (pairs,) float32 xy offset of the point from its sample and its
            square [m, m^2].
        pz: (pairs,) height of the point [m].
        starts: (S,) first pair of each sample.
    """

    S: int
    samples: np.ndarray
    C: np.ndarray
    s_idx: np.ndarray
    p_idx: np.ndarray
    pdx: np.ndarray
    pdy: np.ndarray
    pr2: np.ndarray
    pz: np.ndarray
    starts: np.ndarray


@dataclass(frozen=True)
class HandSweep:
    """The K rotations of every sample's hand over its neighbouring points: (K, pairs).

    Attributes:
        phase: (K,) rotation of each hand from the sample's first closing direction [rad].
        Xg, Yg: (K, pairs) float32 coordinates of the points along x_G and -y_G [m].
        strip: (K, pairs) points between the pads (in the closing region's footprint).
        top: (K, S) highest point between the pads [m].
        finger_z, palm_z: (K, S) highest point in the fingers' / the palm's footprint [m].
        house_z: (1, S) highest point in the housing's round footprint [m].
    """

    phase: np.ndarray
    Xg: np.ndarray
    Yg: np.ndarray
    strip: np.ndarray
    top: np.ndarray
    finger_z: np.ndarray
    palm_z: np.ndarray
    house_z: np.ndarray


def _segments(sorted_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal ids in a sorted array: (start positions, run ids, run index of
    every element)."""
    flag = np.empty(len(sorted_ids), dtype=bool)
    if len(sorted_ids):
        flag[0] = True
        np.not_equal(sorted_ids[1:], sorted_ids[:-1], out=flag[1:])
    starts = np.flatnonzero(flag)
    return starts, sorted_ids[starts], np.cumsum(flag) - 1


def object_points(cloud: OrganizedCloud, obj: np.ndarray, R_WC: np.ndarray,
                  step_threshold_m: float, far: float, st_: dict) -> ObjectPoints:
    """Per-pixel attributes of the object points (`obj`), their objects' centroids and
    radii (for the centring term); counts them in ``st_["points"]``."""
    cn, use_wall = _contact_normals(cloud, R_WC, step_threshold_m, far)
    labels_img, n_labels = ndimage.label(obj, structure=np.ones((3, 3), dtype=int))
    P = cloud.points[obj]  # (M, 3)
    Nc = cn[obj]
    is_wall = use_wall[obj]
    label = labels_img[obj]
    # Area each point stands for, across the optical axis (for the fill term).
    area = (cloud.depth[obj] / cloud.focal_px) ** 2
    # A silhouette's true edge lies between its last pixel's centre and the next
    # pixel's: up to one pixel footprint beyond the point (the collision tests grow
    # the hand by that much around such points), half a pixel on average (widths and
    # contacts are pushed out by that much).
    px_all = np.sqrt(area)
    px_wall = np.where(is_wall, px_all, 0.0)
    half_px = 0.5 * px_wall
    M = len(P)
    st_["points"] = M
    # Objects (connected components): centroid and radius for the centring term.
    cnt_l = np.bincount(label, minlength=n_labels + 1).astype(float)
    cx_l = np.bincount(label, P[:, 0], minlength=n_labels + 1) / np.maximum(cnt_l, 1)
    cy_l = np.bincount(label, P[:, 1], minlength=n_labels + 1) / np.maximum(cnt_l, 1)
    r_pt = np.hypot(P[:, 0] - cx_l[label], P[:, 1] - cy_l[label])
    rad_l = np.zeros(n_labels + 1)
    np.maximum.at(rad_l, label, r_pt)
    return ObjectPoints(P, Nc, is_wall, label, area, px_all, px_wall, half_px,
                        cx_l, cy_l, rad_l)


def sample_neighbourhoods(pts: ObjectPoints, S_max: int, rng: np.random.Generator,
                          st_: dict) -> Neighbourhoods:
    """Draws min(S_max, M) sample points with `rng` (one `choice` call) and pairs each
    with the object points within the hand's footprint radius (grown by the largest
    silhouette pixel); counts the samples in ``st_["samples"]``."""
    P, px_wall = pts.P, pts.px_wall
    M = len(P)
    S = min(S_max, M)
    st_["samples"] = S
    samples = np.sort(rng.choice(M, size=S, replace=False))
    C = P[samples]  # hand axes pass through these points
    dx = (P[None, :, 0] - C[:, None, 0]).astype(np.float32)
    dy = (P[None, :, 1] - C[:, None, 1]).astype(np.float32)
    r2 = dx * dx + dy * dy
    near = r2 <= np.float32(HAND_FOOTPRINT_RADIUS_M + px_wall.max() + 1e-6) ** 2
    s_idx, p_idx = np.nonzero(near)  # sorted by sample: contiguous runs per sample
    pdx, pdy, pr2 = dx[near], dy[near], r2[near]
    pz = P[p_idx, 2]
    starts = np.flatnonzero(np.r_[True, s_idx[1:] != s_idx[:-1]])  # every sample has itself
    return Neighbourhoods(S, samples, C, s_idx, p_idx, pdx, pdy, pr2, pz, starts)


def first_closing_directions(Nc: np.ndarray, nb: Neighbourhoods) -> np.ndarray:
    """(S,) yaw [rad] in [0, pi) of each sample's first closing direction: the contact
    normal made horizontal, or on flat tops the minor axis of the local footprint."""
    S, s_idx, pdx, pdy, pr2 = nb.S, nb.s_idx, nb.pdx, nb.pdy, nb.pr2
    h = Nc[nb.samples, :2]
    h_len = np.linalg.norm(h, axis=1)
    # Flat tops: the minor axis of the local footprint (points within 3 cm).
    fp = pr2 <= _FOOTPRINT_RADIUS_M**2
    cnt = np.bincount(s_idx[fp], minlength=S).astype(float)
    mx = np.bincount(s_idx[fp], pdx[fp], minlength=S) / cnt
    my = np.bincount(s_idx[fp], pdy[fp], minlength=S) / cnt
    cxx = np.bincount(s_idx[fp], pdx[fp] ** 2, minlength=S) / cnt - mx**2
    cyy = np.bincount(s_idx[fp], pdy[fp] ** 2, minlength=S) / cnt - my**2
    cxy = np.bincount(s_idx[fp], pdx[fp] * pdy[fp], minlength=S) / cnt - mx * my
    minor = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy) + 0.5 * np.pi
    base = np.where(h_len > _MIN_HORIZONTAL_NORMAL, np.arctan2(h[:, 1], h[:, 0]), minor)
    return np.mod(base, np.pi)


def sweep_hands(nb: Neighbourhoods, base: np.ndarray, K: int, px_wall: np.ndarray,
                margin: float) -> HandSweep:
    """Hand-frame coordinates of the neighbours for all K rotations, and per hand the
    highest point under the pads, the fingers, the palm and the housing (the parts grown
    by a pixel around silhouette points, the fingers' inner faces by `margin`)."""
    s_idx, p_idx, pdx, pdy, pr2, pz, starts = (nb.s_idx, nb.p_idx, nb.pdx, nb.pdy, nb.pr2,
                                               nb.pz, nb.starts)
    cb, sb = np.cos(base[s_idx]).astype(np.float32), np.sin(base[s_idx]).astype(np.float32)
    x0 = pdx * cb + pdy * sb  # along x_G at rotation 0
    w0 = pdy * cb - pdx * sb  # along -y_G at rotation 0 (only |y| matters)
    phase = np.pi * np.arange(K) / K
    c, s = np.cos(phase).astype(np.float32)[:, None], np.sin(phase).astype(np.float32)[:, None]
    Xg = c * x0 + s * w0
    Yg = c * w0 - s * x0  # -y_G (only symmetric tests and extents use it)
    aY = np.abs(Yg)
    aX = np.abs(Xg)
    zf = pz.astype(np.float32)[None, :]
    ninf = np.float32(-np.inf)
    strip = (aY <= PAD_HALF_WIDTH_M) & (aX <= HALF_STROKE_M)
    # Collisions: the hand's parts are grown by a pixel around silhouette points.
    hp = px_wall[p_idx].astype(np.float32)[None, :]
    finger = ((aY - hp <= PAD_HALF_WIDTH_M) & (aX + hp > HALF_STROKE_M - margin)
              & (aX - hp <= FINGER_OUTER_X_M))
    palm = (aX - hp <= PALM_HALF_X_M) & (aY - hp <= PALM_HALF_Y_M)
    top = np.maximum.reduceat(np.where(strip, zf, ninf), starts, axis=1)  # (K, S)
    finger_z = np.maximum.reduceat(np.where(finger, zf, ninf), starts, axis=1)
    palm_z = np.maximum.reduceat(np.where(palm, zf, ninf), starts, axis=1)
    house = np.where(np.sqrt(pr2) - hp[0] <= HOUSING_RADIUS_M, pz, -np.inf)
    house_z = np.maximum.reduceat(house, starts)[None, :]  # (1, S): round, any rotation
    return HandSweep(phase, Xg, Yg, strip, top, finger_z, palm_z, house_z)


def collision_free_heights(sw: HandSweep, dep: np.ndarray, floor: float, K: int, S: int,
                           st_: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre heights of the hands at the depths `dep` below the local top, the
    fingertips kept above `floor`, and which are collision-free (a depth clamped to
    the same height as the one before counts once); counts both in `st_`.

    Returns:
        zc (K * S, D) centre heights [m], free (K * S, D), top (K * S,) [m], rows by
        hand axis a = k * S + s.
    """
    top, finger_z, palm_z, house_z = sw.top, sw.finger_z, sw.palm_z, sw.house_z
    # Centre heights (K, S, D): `depths` below the local top, fingertips above the floor.
    zc = np.maximum(top[..., None].astype(float) - dep, floor + FINGERTIP_Z_M)
    free = ((finger_z[..., None] < zc - FINGERTIP_Z_M)
            & (palm_z[..., None] < zc - PALM_FRONT_Z_M)
            & (house_z[..., None] < zc - HOUSING_FRONT_Z_M))
    distinct = np.ones(zc.shape, dtype=bool)
    distinct[..., 1:] = zc[..., 1:] < zc[..., :-1] - 1e-9  # clamped depths: one copy
    free &= distinct
    st_["hands"] = int(distinct.sum())
    st_["collision_free"] = int(free.sum())
    A = K * S
    zc = zc.reshape(A, -1)
    free = free.reshape(A, -1)
    top = top.reshape(A).astype(float)
    return zc, free, top


def _contact_patches(gi: np.ndarray, G: int, pt: np.ndarray, patches, zcon: np.ndarray,
                     pts: ObjectPoints):
    """Centroid and mean unit normal of each hand's two contact patches (-x_G side
    first), and the sums over both patches of their points' labels, squared labels
    and counts (to test that both lie on one object)."""
    P, Nc, label = pts.P, pts.Nc, pts.label
    sides = []
    lab_sum = np.zeros(G)
    lab_sq = np.zeros(G)
    lab_n = np.zeros(G)
    for patch in patches:
        g = gi[patch]
        q = pt[patch]
        num = np.bincount(g, minlength=G).astype(float)
        pos = np.stack([np.bincount(g, P[q, 0], minlength=G),
                        np.bincount(g, P[q, 1], minlength=G),
                        np.bincount(g, zcon[patch], minlength=G)], axis=1) / num[:, None]
        nrm = np.stack([np.bincount(g, Nc[q, j], minlength=G) for j in range(3)], axis=1)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        lq = label[q].astype(float)
        lab_sum += np.bincount(g, lq, minlength=G)
        lab_sq += np.bincount(g, lq * lq, minlength=G)
        lab_n += num
        sides.append((pos, nrm))
    return sides, lab_sum, lab_sq, lab_n


def _closing_hands_at_depth(out: dict, di: int, zc: np.ndarray, free: np.ndarray, strip_pts,
                            pts: ObjectPoints, min_points_between: int, min_width_m: float,
                            tol: float, mu: float, st_: dict) -> None:
    """The collision-free hands at depth index `di` with enough points between the
    pads, one object and force-closure contacts: appended to `out` by key."""
    e_axis, e_x, e_pt, e_z = strip_pts
    P, is_wall, half_px, px_all, area = pts.P, pts.is_wall, pts.half_px, pts.px_all, pts.area
    z_lo = zc[:, di] - PAD_HALF_LENGTH_M
    m = np.flatnonzero((e_z >= z_lo[e_axis]) & free[e_axis, di])
    if len(m) == 0:
        return
    ids = e_axis[m]
    st, grp, gi = _segments(ids)
    G = len(grp)
    pt = e_pt[m]
    # Silhouette points pushed out by half a pixel: unbiased widths, clearances.
    x = e_x[m].astype(float)
    x_lo = np.maximum(x - half_px[pt], -HALF_STROKE_M)
    x_hi = np.minimum(x + half_px[pt], HALF_STROKE_M)
    xmin = np.minimum.reduceat(x_lo, st)
    xmax = np.maximum.reduceat(x_hi, st)
    count = np.diff(np.r_[st, len(m)])
    lo_m, hi_m = z_lo[ids], z_lo[ids] + 2.0 * PAD_HALF_LENGTH_M
    zp = P[pt, 2]
    # Contact height: on a wall, the middle of its part within the pads; on a
    # visible surface, the point itself (clipped to the pads).
    zcon = np.where(is_wall[pt], 0.5 * (lo_m + np.minimum(zp, hi_m)),
                    np.clip(zp, lo_m, hi_m))
    tol_pt = np.maximum(tol, px_all[pt])
    patches = (x_lo <= xmin[gi] + tol_pt, x_hi >= xmax[gi] - tol_pt)
    sides, lab_sum, lab_sq, lab_n = _contact_patches(gi, G, pt, patches, zcon, pts)
    mean_l = lab_sum / lab_n
    one_object = np.abs(lab_sq / lab_n - mean_l**2) < 1e-6
    width = xmax - xmin
    ok = (count >= min_points_between) & (width >= min_width_m) & one_object
    st_["closing_region"] += int(ok.sum())
    ok &= force_closure(sides[0][0], sides[0][1], sides[1][0], sides[1][1], mu=mu)
    keep = np.flatnonzero(ok)
    st_["antipodal"] += len(keep)
    out["axis"].append(grp[keep])
    out["d"].append(np.full(len(keep), di))
    out["count"].append(count[keep])
    out["xmin"].append(xmin[keep])
    out["xmax"].append(xmax[keep])
    out["c0"].append(sides[0][0][keep])
    out["c1"].append(sides[1][0][keep])
    out["n0"].append(sides[0][1][keep])
    out["n1"].append(sides[1][1][keep])
    out["label"].append(np.rint(mean_l[keep]).astype(np.int64))
    out["area"].append(np.bincount(gi, area[pt], minlength=G)[keep])


def closing_contacts(nb: Neighbourhoods, sw: HandSweep, pts: ObjectPoints, zc: np.ndarray,
                     free: np.ndarray, D: int, *, min_points_between: int, min_width_m: float,
                     tol: float, mu: float, st_: dict) -> dict | None:
    """Closing region and contacts of the collision-free hands, over the D depths.

    Returns:
        Arrays by `CONTACT_KEYS` over the surviving hands (depth-major): hand axis,
        depth index, points between the pads, closing extent along x_G, contact
        centroids and normals, object label and covered area; None when none survive.
    """
    S, s_idx, p_idx, pz = nb.S, nb.s_idx, nb.p_idx, nb.pz
    e = np.flatnonzero(sw.strip)  # k-major, then by pair: axis ids a = k * S + s sorted
    e_k, e_pair = np.divmod(e, len(s_idx))
    e_axis = e_k * S + s_idx[e_pair]
    e_x = sw.Xg.ravel()[e]
    e_pt = p_idx[e_pair]
    e_z = pz[e_pair]
    out = {k: [] for k in CONTACT_KEYS}
    for di in range(D):  # a handful of depths
        _closing_hands_at_depth(out, di, zc, free, (e_axis, e_x, e_pt, e_z), pts,
                                min_points_between, min_width_m, tol, mu, st_)
    if not out["axis"] or sum(len(a) for a in out["axis"]) == 0:
        return None
    return {k: np.concatenate(v) for k, v in out.items()}


def survivor_poses(r: dict, S: int, base: np.ndarray, phase: np.ndarray, C: np.ndarray,
                   zc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw [rad] of x_G and the grasp centre (x, y, z) [m] of each surviving hand."""
    axis, di = r["axis"], r["d"]
    k_of, s_of = np.divmod(axis, S)
    yaw = base[s_of] + phase[k_of]
    centre = np.column_stack([C[s_of, :2], zc[axis, di]])
    return yaw, centre
