"""The distance CNN's "window" head (`NetworkConfig.action_fusion == "window"`): the net
looks where the candidate grasp would be. This module owns `WindowHead`, the head
`drake_grasp.cnn.network.DistanceCNN` delegates to for it: the image features (lrelu of
Conv2 on the shared trunk, kept unpooled, with a channel holding the image's reference
depth, `WindowHead.reference_depth`), the sampling grid of each candidate's window (and
its optional coarser context window) on that map, turned by the candidate's angle and
placed by the camera's geometry (`WindowHead.window_grid`), and the scores: the windows
sampled, pooled 2x2, through IP1 plus the angle's and depth's share (`WindowHead.scores`).
"""

from typing import Optional

import torch
import torch.nn.functional as F


class WindowHead:
    """The window fusion's head on the `DistanceCNN` `net`'s shared trunk. Holds only the
    net (whose layers it reads) and is made afresh by `DistanceCNN.head`."""

    def __init__(self, net) -> None:
        self.net = net

    def direct(self, images: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """(B,) distances for one action's features (B, 4) per image."""
        return self.scores(self.net.image_features(images), feats[:, None])[:, 0]

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """lrelu(Conv2) of the trunk and the reference-depth channel, (B, C2 + 1, S, S)."""
        net = self.net
        fmap = net._lrelu(net.conv2(net.trunk(images)))
        ref = self.reference_depth(images)[:, None, None, None]
        return torch.cat((fmap, ref.expand(-1, 1, *fmap.shape[2:])), dim=1)

    def score_one(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (K,) for K actions' features (K, 4) on one image's features."""
        return self.scores(features[None], feats[None])[0]

    def reference_depth(self, images: torch.Tensor) -> torch.Tensor:
        """Each image's median depth [m] (clipped as the input is): the depth at which a
        candidate's (x, y) in metres is placed in the image. (B,)"""
        cfg = self.net.config
        depth = images.flatten(1) * cfg.depth_scale_m + cfg.depth_offset_m
        return depth.median(dim=1).values

    def window_grid(self, feats: torch.Tensor, ref: torch.Tensor,
                    side_m: Optional[float] = None) -> torch.Tensor:
        """grid_sample coordinates of every candidate's window on the lrelu(Conv2) map.

        Args:
            feats: (B, M, 4) action features; ref: (B,) reference depths [m].
            side_m: The window's side [m]; default `window_side_m`.

        Returns:
            (B, M * n, n, 2), n = `window_samples`, in align_corners=True units.
        """
        cfg = self.net.config
        n = cfg.window_samples
        side = cfg.feature_shape()[1]  # the Conv2 map's side (26 for the defaults)
        centre = feats[..., :2] * cfg.action_xy_scale_m  # (B, M, 2) in G [m]
        # theta from (cos 2theta, sin 2theta), in (-90, 90] degrees: the window's x axis
        # (the closing direction) is at +theta in the (x_G, y_G) = (u, v) plane.
        theta = 0.5 * torch.atan2(feats[..., 3], feats[..., 2])
        e1 = torch.stack((torch.cos(theta), torch.sin(theta)), dim=-1)  # (B, M, 2)
        e2 = torch.stack((-torch.sin(theta), torch.cos(theta)), dim=-1)
        step = (cfg.window_side_m if side_m is None else side_m) / n
        s = (torch.arange(n, dtype=feats.dtype, device=feats.device) - (n - 1) / 2.0) * step
        # points[b, m, i, j] = centre + s[j] e1 + s[i] e2 (row i along e2, column j along e1)
        pts = (centre[:, :, None, None, :] + s[None, None, None, :, None] * e1[:, :, None, None, :]
               + s[None, None, :, None, None] * e2[:, :, None, None, :])
        cam = torch.tensor([cfg.camera_x_G_m, cfg.camera_y_G_m], dtype=feats.dtype,
                           device=feats.device)
        pixels = ((pts - cam) * (cfg.focal_px / ref[:, None, None, None, None])
                  + (cfg.image_size / 2.0 - 0.5))  # (u, v) in input pixels
        # Conv2 output j sees input pixels centred at 2j + 3 (k - 1) / 2 + 0.5 (k = 5: 2j + 6.5).
        k = cfg.kernel
        centre0 = (k - 1) / 2.0 + 2.0 * (k - 1) / 2.0 + 0.5
        grid = (pixels - centre0) / 2.0 * (2.0 / (side - 1)) - 1.0
        b, m = feats.shape[:2]
        return grid.reshape(b, m * n, n, 2)

    def scores(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances for M actions on each of B images from `image_features`.

        Args:
            features: (B, C2 + 1, S, S): lrelu(Conv2) and the reference-depth channel.
            feats: (B, M, 4) action features.

        Returns:
            (B, M).
        """
        cfg = self.net.config
        b, m = feats.shape[:2]
        n = cfg.window_samples
        fmap, ref = features[:, :-1], features[:, -1, 0, 0]
        c2, half = fmap.shape[1], n // 2
        sides = [cfg.window_side_m] + ([cfg.context_side_m] if cfg.context_side_m > 0 else [])
        parts = []
        for side_m in sides:
            grid = self.window_grid(feats, ref, side_m)
            win = F.grid_sample(fmap, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)  # (B, C2, M * n, n)
            # 2x2 max-pool in place (n is even: no block straddles two windows), then
            # the 4x smaller result goes to one row per candidate. (Four strided maxima:
            # ~10x faster on CPU than max_pool2d or amax here.)
            w = win.reshape(b, c2, m * half, 2, half, 2)
            win = torch.maximum(torch.maximum(w[:, :, :, 0, :, 0], w[:, :, :, 0, :, 1]),
                                torch.maximum(w[:, :, :, 1, :, 0], w[:, :, :, 1, :, 1]))
            parts.append(win.reshape(b, c2, m, half * half).transpose(1, 2)
                         .reshape(b * m, c2 * half * half))
        h = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        z = (ref - cfg.depth_offset_m) / cfg.depth_scale_m
        extra = torch.cat((feats[..., 2:], z[:, None, None].expand(b, m, 1)),
                          dim=-1).reshape(b * m, 3)
        net = self.net
        y = net.ip1(h) + net.ip_action(extra)
        return net._after_ip1(y).reshape(b, m)
