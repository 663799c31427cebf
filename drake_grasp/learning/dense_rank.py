"""The grid head's pairwise rank loss, the optional term `drake_grasp.learning.
dense_training.train(rank_weight=...)` adds to the L1: pairs of nearby grid nodes drawn
per image (`rank_pairs`, at most `RANK_REACH_CELLS` apart along each axis, theta
wrapping), their predicted and label gaps (`rank_pair_gaps`), and RankNet's logistic loss
of ordering each pair as its labels do (`pairwise_rank_loss`): the L1 asks every node for
its distance, this asks only that nearby nodes come in the order of their distances.
"""

import numpy as np
import torch
import torch.nn.functional as F

# The controller picks the lowest-scored of candidates near the hand (within 4 cm and 45
# degrees: `ControllerConfig.sample_xy_m`, `sample_theta_deg`), so what it needs of the net
# is the order of nearby nodes. `rank_pairs` draws pairs of grid nodes that near each other
# (4 cells = 4 cm in x and y, 4 bins = 40 degrees in theta, theta wrapping over 180).
RANK_REACH_CELLS = 4


def rank_pairs(grid_shape: tuple[int, int, int], images: int, pairs: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`pairs` pairs of nearby grid nodes per image, as flat node indices (images, pairs)
    into a (theta, y, x) grid of `grid_shape`: an anchor anywhere on the grid and a
    partner at most `RANK_REACH_CELLS` away along each axis (theta wrapping over 180
    degrees), never the anchor itself. Partners off the grid in x or y get index -1."""
    t_bins, n, _ = grid_shape
    r = RANK_REACH_CELLS
    anchor = np.stack([rng.integers(0, t_bins, (images, pairs)),
                       rng.integers(0, n, (images, pairs)),
                       rng.integers(0, n, (images, pairs))])
    step = rng.integers(-r, r + 1, (3, images, pairs))
    still = (step == 0).all(axis=0)
    step[2][still] = rng.choice([-1, 1], int(still.sum()))  # never the anchor itself
    t = np.mod(anchor[0] + step[0], t_bins)
    y, x = anchor[1] + step[1], anchor[2] + step[2]
    first = (anchor[0] * n + anchor[1]) * n + anchor[2]
    second = np.where((y >= 0) & (y < n) & (x >= 0) & (x < n), (t * n + y) * n + x, -1)
    return first, second


def pairwise_rank_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                       first: np.ndarray, second: np.ndarray, *, scale_m: float,
                       margin_m: float) -> torch.Tensor:
    """The mean logistic loss of ordering pairs of grid nodes of each image as their
    labels do: for nodes i, j of one image with labels t_i < t_j - `margin_m`, both counted
    by `mask`, softplus(-(p_j - p_i) / `scale_m`) (RankNet's loss on the predicted
    distances p). `first`, `second`: (images, pairs) flat node indices (`rank_pairs`; -1
    = no partner). 0 when no pair counts. Added to the L1 by `train(rank_weight=...)`:
    the L1 asks every node for its distance, this asks only that nearby nodes come in the
    order of their distances, which is all the controller's choice uses."""
    pred_gap, label_gap, valid = rank_pair_gaps(pred, target, mask, first, second,
                                                margin_m=margin_m)
    if not bool(valid.any()):
        return pred.sum() * 0.0
    z = torch.sign(label_gap) * pred_gap / scale_m
    return F.softplus(-z)[valid].mean()


def rank_pair_gaps(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                   first: np.ndarray, second: np.ndarray, *, margin_m: float) -> tuple:
    """For the pairs (`first`, `second`) of `rank_pairs`: the predicted gaps p_j - p_i,
    the label gaps t_j - t_i, and which pairs count (both nodes counted by `mask`, a
    partner on the grid, labels more than `margin_m` apart); each (images, pairs)."""
    b = pred.shape[0]
    p, t, m = pred.reshape(b, -1), target.reshape(b, -1), mask.reshape(b, -1)
    i = torch.from_numpy(first).to(pred.device)
    j_raw = torch.from_numpy(second).to(pred.device)
    j = j_raw.clamp(min=0)
    label_gap = t.gather(1, j) - t.gather(1, i)
    valid = m.gather(1, i) & m.gather(1, j) & (j_raw >= 0) & (label_gap.abs() > margin_m)
    return p.gather(1, j) - p.gather(1, i), label_gap, valid

