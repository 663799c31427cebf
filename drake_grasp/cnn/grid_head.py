"""The distance CNN's "grid" head (`NetworkConfig.action_fusion == "grid"`): the shared
trunk without an action input, then IP2 predicting the distance at every node of a grid
of actions (x, y around the camera's centre, theta over 180 degrees). This module owns
that grid: the nodes around an action and their trilinear weights (`grid_corners`), the
interpolation of a distance grid at actions (`grid_scores`), the nodes inside the
camera's view (`grid_view_mask`), and `GridHead`, the head
`drake_grasp.cnn.network.DistanceCNN` delegates to for it: the trunk up to IP2's input
(`GridHead.hidden`), the whole grid from it (`GridHead.grid_from_hidden`) and the control
path that runs IP2 only at the nodes a set of candidates needs (`GridHead.score_nodes`).
"""

import numpy as np
import torch
import torch.nn.functional as F

from drake_grasp.cnn.net_config import NetworkConfig
from drake_grasp.geometry.camera import view_half_extent_m


def grid_corners(cfg: "NetworkConfig", feats: torch.Tensor) -> list:
    """The 8 grid nodes around each of M actions on B images and their trilinear
    weights: [(flat node index (B, M), weight (B, M))] (see `grid_scores`); the grid is
    `cfg`'s (`NetworkConfig.grid_shape`, its step, theta step and camera offset)."""
    t_bins, n, _ = cfg.grid_shape()
    b, m = feats.shape[:2]
    half = (n - 1) / 2.0
    # Node coordinates: x = camera_x + (i - half) step, theta = -90 + k step.
    u = (feats[..., 0] * cfg.action_xy_scale_m - cfg.camera_x_G_m) / cfg.grid_step_m + half
    v = (feats[..., 1] * cfg.action_xy_scale_m - cfg.camera_y_G_m) / cfg.grid_step_m + half
    theta_deg = torch.rad2deg(0.5 * torch.atan2(feats[..., 3], feats[..., 2]))
    w = torch.remainder((theta_deg + 90.0) / cfg.grid_theta_step_deg, float(t_bins))
    u = u.clamp(0.0, n - 1.0)
    v = v.clamp(0.0, n - 1.0)
    iu = u.detach().floor().clamp(max=n - 2).long()
    iv = v.detach().floor().clamp(max=n - 2).long()
    iw = w.detach().floor().long().clamp(0, t_bins - 1)
    fu, fv, fw = u - iu, v - iv, w - iw
    iw1 = torch.remainder(iw + 1, t_bins)
    corners = []
    for kw, gw in ((iw, 1.0 - fw), (iw1, fw)):
        for kv, gv in ((iv, 1.0 - fv), (iv + 1, fv)):
            for ku, gu in ((iu, 1.0 - fu), (iu + 1, fu)):
                corners.append(((kw * n + kv) * n + ku, gw * gv * gu))
    return corners


def grid_view_mask(camera_height_m, cfg: "NetworkConfig", *, slack_m: float = 1e-9) -> np.ndarray:
    """(B, N) mask of the grid's x (and, the view being square, y) nodes inside the
    camera's footprint on the table at each of B camera heights above it [m], widened by
    `slack_m`."""
    n = cfg.grid_shape()[1]
    half_view = np.atleast_1d(view_half_extent_m(camera_height_m, cfg.camera_fov_deg))
    offsets = (np.arange(n) - (n - 1) / 2.0) * cfg.grid_step_m
    return np.abs(offsets)[None, :] <= half_view[:, None] + slack_m


def grid_scores(cfg: "NetworkConfig", grids: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
    """Distances for M actions on each of B images from their distance grids: the
    trilinear interpolation between the 8 grid nodes around each action, periodic in
    theta (a parallel jaw turned by 180 degrees is the same grasp); x and y beyond
    the grid are clamped to its edge.

    Args:
        grids: (B, T, N, N) from `image_features` (theta, y, x).
        feats: (B, M, 4) action features.

    Returns:
        (B, M).
    """
    flat = grids.reshape(grids.shape[0], -1)
    out = 0.0
    for idx, weight in grid_corners(cfg, feats):
        out = out + torch.gather(flat, 1, idx) * weight
    return out


class GridHead:
    """The grid head on the `DistanceCNN` `net`'s shared trunk. Holds only the net (whose
    layers it reads) and is made afresh by `DistanceCNN.head`."""

    def __init__(self, net) -> None:
        self.net = net

    def direct(self, images: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """(B,) distances for one action's features (B, 4) per image."""
        return self.scores(self.net.image_features(images), feats[:, None])[:, 0]

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """The whole distance grid of each image, (B, T, N, N)."""
        return self.grid_from_hidden(self.hidden(images))

    def scores(self, grids: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (B, M) for M actions' features (B, M, 4) from grids (`grid_scores`)."""
        return grid_scores(self.net.config, grids, feats)

    def score_one(self, grid: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (K,) for K actions' features (K, 4) on one image's grid."""
        return self.scores(grid[None], feats[None])[0]

    def grid_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        """The whole distance grid, (..., T, N, N), from `hidden` (..., ip1)."""
        net = self.net
        z = net.ip2(hidden)
        return (net.config.output_scale_m * F.softplus(z)).reshape(
            *hidden.shape[:-1], *net.config.grid_shape())

    def hidden(self, images: torch.Tensor) -> torch.Tensor:
        """`DistanceCNN.grid_hidden`: the trunk up to IP2's input, lrelu(IP1(...)),
        (B, ip1)."""
        net = self.net
        x = net.trunk(images)
        h = F.max_pool2d(net._lrelu(net.conv2(x)), 2).flatten(1)
        return net._lrelu(net.ip1(h))

    def score_nodes(self, hidden: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """`DistanceCNN.score_grid_nodes`: distances for K actions' features (K, 4) on one
        image from its `hidden` (ip1,), IP2 computed only at the grid nodes around
        them, (K,)."""
        net = self.net
        if 4 * 8 * feats.shape[0] > net.ip2.out_features:
            # Many actions (e.g. 2,048 over the whole view need ~40% of the nodes):
            # gathering rows costs more than IP2 over the whole grid.
            grids = self.grid_from_hidden(hidden)
            return grid_scores(net.config, grids[None], feats[None])[0]
        corners = grid_corners(net.config, feats[None])
        nodes, where = torch.unique(torch.cat([idx for idx, _ in corners], dim=1),
                                    return_inverse=True)
        z = F.linear(hidden, net.ip2.weight[nodes], net.ip2.bias[nodes])
        values = net.config.output_scale_m * F.softplus(z)
        k = feats.shape[0]
        out = 0.0
        for j, (_, weight) in enumerate(corners):
            out = out + values[where[:, j * k:(j + 1) * k]] * weight
        return out[0]
