"""The geometric detector's score (stage 5) and its sorted detections.

`score_terms` computes, for the hands that passed every test, the seven terms of the
documented geometric score, each in [0, 1] (antipodal margin inside the friction cone,
centring on the grasped object, balance of the object between the pads, clearance to
the open fingers, fill of the pads' area, depth of the pads below the local top, and
a small view tie-breaker; see `gpd_geometric`'s module docstring), and
`sorted_detections` weighs them (`ScoreWeights`) and returns the `DetectedGrasps`
best first, with theta the yaw of x_G in degrees modulo 180 and the contacts listed
along it. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.geometry.camera import view_half_extent_m
from drake_grasp.geometry.hand_model import PAD_HALF_LENGTH_M, PAD_HALF_WIDTH_M
from drake_grasp.policies.gpd_geometric_hands import (
    HALF_STROKE_M,
    HandSweep,
    Neighbourhoods,
    ObjectPoints,
)
from drake_grasp.policies.gpd_geometric_results import SCORE_TERMS, DetectedGrasps, ScoreWeights

# Half length along y_G of the window in which the balance term measures the
# object's extent [m]: the hand's half width, roughly.
_BALANCE_HALF_WINDOW_M = 0.04


def _antipodal_term(r: dict, mu: float, n: int) -> np.ndarray:
    """1 - max(angle_1, angle_2) / atan(mu): the contact normals' margin inside the
    friction cone (1 for mu = 0)."""
    c0, c1, n0, n1 = r["c0"], r["c1"], r["n0"], r["n1"]
    line = c1 - c0
    line /= np.maximum(np.linalg.norm(line, axis=1, keepdims=True), 1e-12)
    ang0 = np.arccos(np.clip(-np.sum(line * n0, axis=1), -1.0, 1.0))
    ang1 = np.arccos(np.clip(np.sum(line * n1, axis=1), -1.0, 1.0))
    cone = np.arctan(mu)
    return (np.clip(1.0 - np.maximum(ang0, ang1) / cone, 0.0, 1.0) if cone > 0
            else np.ones(n))


def _balance_term(axis: np.ndarray, centre: np.ndarray, S: int, nb: Neighbourhoods,
                  sw: HandSweep) -> np.ndarray:
    """1 - |y_mid| / 40 mm, y_mid the middle of the object's extent along y_G between
    the fingers.

    The object's extent along y_G between the fingers, within the pads' reach (z >= their
    lower edge) and `_BALANCE_HALF_WINDOW_M` of the centre, should be symmetric about
    the centre (a bottle's cap held across its middle, not by its rim). Over each
    survivor's neighbour pairs, grouped by survivor.
    """
    starts, s_idx, pz, Xg, Yg = nb.starts, nb.s_idx, nb.pz, sw.Xg, sw.Yg
    k_of, s_of = np.divmod(axis, S)
    ends = np.r_[starts[1:], len(s_idx)]
    lens = ends[s_of] - starts[s_of]
    owner = np.repeat(np.arange(len(axis)), lens)
    pos = starts[s_of][owner] + np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
    bx, by = Xg[k_of[owner], pos], Yg[k_of[owner], pos]
    inb = ((np.abs(bx) <= HALF_STROKE_M) & (np.abs(by) <= _BALANCE_HALF_WINDOW_M)
           & (pz[pos] >= (centre[:, 2] - PAD_HALF_LENGTH_M)[owner]))
    first = np.r_[0, np.cumsum(lens)[:-1]]
    y_lo = np.minimum.reduceat(np.where(inb, by, np.inf), first)
    y_hi = np.maximum.reduceat(np.where(inb, by, -np.inf), first)
    with np.errstate(invalid="ignore"):
        mid = np.abs(0.5 * (y_lo + y_hi))
    return 1.0 - np.clip(np.nan_to_num(mid, nan=0.0) / _BALANCE_HALF_WINDOW_M, 0.0, 1.0)


def score_terms(r: dict, axis: np.ndarray, centre: np.ndarray, width: np.ndarray,
                top: np.ndarray, *, S: int, nb: Neighbourhoods, sw: HandSweep,
                pts: ObjectPoints, mu: float, p_WC: np.ndarray, table_z: float,
                fov_y_deg: float) -> dict:
    """The score terms by name (`SCORE_TERMS`), each (N,) in [0, 1], of the N hands
    (`r`, their axes, centres [m], closing widths [m]); `top` (K * S,) the local tops."""
    antipodal = _antipodal_term(r, mu, len(axis))
    lab = r["label"]
    d_obj = np.hypot(centre[:, 0] - pts.cx_l[lab], centre[:, 1] - pts.cy_l[lab])
    centring = 1.0 - np.clip(d_obj / np.maximum(pts.rad_l[lab], 1e-6), 0.0, 1.0)
    balance = _balance_term(axis, centre, S, nb, sw)
    clearance = np.clip(np.minimum(HALF_STROKE_M + r["xmin"], HALF_STROKE_M - r["xmax"])
                        / HALF_STROKE_M, 0.0, 1.0)
    fill = np.clip(r["area"] / (np.maximum(width, 1e-3) * 2.0 * PAD_HALF_WIDTH_M), 0.0, 1.0)
    depth_term = np.clip((np.minimum(centre[:, 2] + PAD_HALF_LENGTH_M, top[axis])
                          - (centre[:, 2] - PAD_HALF_LENGTH_M)) / (2.0 * PAD_HALF_LENGTH_M),
                         0.0, 1.0)
    half_view = float(view_half_extent_m(max(p_WC[2] - table_z, 1e-3), float(fov_y_deg)))
    view = 1.0 - np.clip(np.hypot(centre[:, 0] - p_WC[0], centre[:, 1] - p_WC[1]) / half_view,
                         0.0, 1.0)
    return {"antipodal": antipodal, "centring": centring, "balance": balance,
            "clearance": clearance,
            "fill": fill, "depth": depth_term, "view": view}


def sorted_detections(r: dict, yaw: np.ndarray, centre: np.ndarray, width: np.ndarray,
                      terms: dict, weights: ScoreWeights) -> DetectedGrasps:
    """The weighted score and the detections sorted by it, best first (a stable sort),
    theta in [0, 180) and the contacts listed along the reported x_G."""
    c0, c1, n0, n1 = r["c0"], r["c1"], r["n0"], r["n1"]
    score = sum(getattr(weights, k) * terms[k] for k in SCORE_TERMS)
    order = np.argsort(-score, kind="stable")
    yaw_deg = np.mod(np.rad2deg(yaw), 360.0)
    theta = np.mod(yaw_deg, 180.0)
    theta = np.where(theta >= 180.0, 0.0, theta)  # mod of a tiny negative can give 180
    # Reported x_G is at theta: list the contacts along it (-x_G side first).
    flip = (yaw_deg >= 180.0) & (yaw_deg < 360.0)
    c0, c1 = np.where(flip[:, None], c1, c0), np.where(flip[:, None], c0, c1)
    n0, n1 = np.where(flip[:, None], n1, n0), np.where(flip[:, None], n0, n1)
    return DetectedGrasps(
        xy_theta=np.column_stack([centre[:, :2], theta])[order],
        z=centre[order, 2],
        width=width[order],
        score=score[order],
        contacts=np.stack([c0, c1], axis=1)[order],
        contact_normals=np.stack([n0, n1], axis=1)[order],
        terms={k: v_[order] for k, v_ in terms.items()},
    )
