"""The distance CNN of Viereck et al. (CoRL 2017) and its exact factored fast path.

The network estimates d(I, a) >= 0, the distance (metres in the paper's weighted
(x, y, theta) pose space) from the hand, after a planar displacement a = (x, y, theta),
to the nearest viable grasp, given a 64x64 wrist depth image I.

Architecture (the paper's LeNet variant)::

    I (1x64x64) -> Conv1 20@5x5 -> lrelu -> maxpool2 -> (+ tile(IP_a(a)))      30x30
                -> Conv2 50@5x5 -> lrelu -> maxpool2 -> flatten (8450)          13x13
                -> IP1 500 -> lrelu -> IP2 1 -> output_scale_m * softplus -> d

The fast path rests on two exact identities (DESIGN.md, "The CNN, and why it can be
fast"):

1. Conv2 is linear and unpadded, so for a spatially constant per-channel shift b,
   ``Conv2(P + tile(b)) = Conv2(P) + c`` with ``c[o] = sum_i b[i] * sum_taps W2[o, i]``:
   one number per output channel, the conv bias staying inside ``Conv2(P)``.
2. Max-pooling commutes with adding a per-channel constant and with any
   non-decreasing function, so ``pool(lrelu(Z + c)) = lrelu(pool(Z) + c)``.

Hence ``Zp = pool(Conv2(Pool1(lrelu(Conv1(I)))))`` (50x13x13) is computed once per
image (`DistanceCNN.image_features`), and each action costs an affine 4 -> 50 map, a
broadcast add, lrelu and the IP layers (`DistanceCNN.score_actions` for control,
`DistanceCNN.forward_factored` for training). Results equal the direct form up to
floating-point rounding, gradients included.

For control (one image, K candidates, no gradient) IP1 is split further
(`DistanceCNN._ip1_split`). IP1's input is ``lrelu(Zp[j, p] + c_k[j])``; an input whose
argument has the same sign for all K candidates (``Zp[j, p] + min_k c_k[j] > 0``, or
``Zp[j, p] + max_k c_k[j] <= 0``) is affine in c_k, so its share of IP1 is one
matrix-vector pass over the weights for all K together. Only the remaining inputs
(about 20-30% on the wrist images measured) go through the per-candidate product.
Same numbers up to summation order.

This module owns the model: its layers (their attribute names are the weights files'
tensor names), the shared trunk and the three forms above. The config and input encoding
are `drake_grasp.cnn.net_config`'s; each action fusion's cache and fast path is its own
module, which the model delegates to (`tiled_fusion`, `window_fusion`, `grid_head`);
test-time mirror averaging is `drake_grasp.cnn.mirror`'s and weights I/O (safetensors
only, verified on load) `drake_grasp.cnn.weights_io`'s. It knows nothing of Drake;
`drake_grasp.systems` wraps it.
"""

# No `from __future__ import annotations`: NetworkConfig may be nested in scenario
# dataclasses read by Drake's yaml_load_typed, which needs real annotation objects.

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from drake_grasp.cnn import grid_head, tiled_fusion, window_fusion
from drake_grasp.cnn.net_config import ArrayLike, NetworkConfig, action_features, normalize_depth


class DistanceCNN(nn.Module):
    """The paper's distance-to-nearest-grasp CNN, with an exact factored fast path.

    Inputs are *normalized* images (`normalize_depth`, or `preprocess`) and actions
    as raw (x, y, theta) or as features (`action_features`).

    Three equal forms (up to rounding):

    * `forward` / `forward_direct`: the paper's graph, (B images, B actions) -> (B,).
    * `image_features` + `score_actions`: control; one image, K candidate actions.
    * `forward_factored`: training; B images, each with M labelled actions -> (B, M).

    Construction never touches torch's global RNG: the layers are created on the meta
    device and initialised from `generator` (a fresh generator seeded 0 by default).

    Args:
        config: Architecture and normalization; defaults to `NetworkConfig()`.
        generator: Source of the initial weights.
        dtype: Floating dtype of the parameters.
    """

    def __init__(
        self,
        config: Optional[NetworkConfig] = None,
        *,
        generator: Optional[torch.Generator] = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        self.config = config if config is not None else NetworkConfig()
        cfg = self.config
        meta = {"device": "meta", "dtype": dtype}
        self.window = cfg.action_fusion == "window"
        self.grid = cfg.action_fusion == "grid"
        self.conv1 = nn.Conv2d(1, cfg.conv1_channels, cfg.kernel, **meta)
        # Window fusion: the action's angle and the reference depth go to IP1's output
        # (not x, y: where the candidate lies is where the window lies). The grid head
        # has no action input.
        self.ip_action = (nn.Linear(3, cfg.ip1, **meta) if self.window
                          else None if self.grid
                          else nn.Linear(4, cfg.conv1_channels, **meta))
        self.conv2 = nn.Conv2d(cfg.conv1_channels, cfg.conv2_channels, cfg.kernel, **meta)
        self.ip1 = nn.Linear(cfg.num_features, cfg.ip1, **meta)
        outputs = math.prod(cfg.grid_shape()) if self.grid else 1
        self.ip2 = nn.Linear(cfg.ip1, outputs, **meta)
        # Module.to_empty would do the same, but its first call imports torch's symbolic
        # shape machinery (~0.4 s of every worker process's start).
        for layer in self.children():
            for name, p in list(layer.named_parameters(recurse=False)):
                setattr(layer, name, nn.Parameter(torch.empty(p.shape, dtype=p.dtype)))
        self.reset_parameters(generator)

    @torch.no_grad()
    def reset_parameters(self, generator: Optional[torch.Generator] = None) -> None:
        """He-uniform weights (for leaky ReLU), uniform +-1/sqrt(fan_in) biases.

        Args:
            generator: Random source; None means a fresh generator seeded 0.
        """
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        for layer in (self.conv1, self.ip_action, self.conv2, self.ip1, self.ip2):
            if layer is None:
                continue
            nn.init.kaiming_uniform_(
                layer.weight, a=self.config.leaky_slope, nonlinearity="leaky_relu", generator=g
            )
            fan_in = layer.weight[0].numel()
            bound = 1.0 / math.sqrt(fan_in)
            layer.bias.uniform_(-bound, bound, generator=g)

    # -- helpers -------------------------------------------------------------------

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the parameters."""
        return self.conv1.weight.dtype

    def preprocess(self, depth: ArrayLike) -> torch.Tensor:
        """`normalize_depth` with this net's config and dtype -> (B, 1, H, W)."""
        return normalize_depth(depth, self.config, dtype=self.dtype)

    def _lrelu(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(x, self.config.leaky_slope)

    def _check_images(self, images: torch.Tensor) -> None:
        s = self.config.image_size
        if images.ndim != 4 or tuple(images.shape[1:]) != (1, s, s):
            raise ValueError(
                f"images: expected shape (B, 1, {s}, {s}) (normalized depth), "
                f"got {tuple(images.shape)}"
            )

    def _features(self, actions: ArrayLike) -> torch.Tensor:
        return action_features(actions, self.config, dtype=self.dtype)

    def _head(self, h: torch.Tensor, *, fast_ip1: bool = False) -> torch.Tensor:
        """IP1 -> lrelu -> IP2 -> scaled softplus on flattened Pool2 activations."""
        y = self._ip1_packed(h) if fast_ip1 else None
        if y is None:
            y = self.ip1(h)
        return self._after_ip1(y)

    def _after_ip1(self, y: torch.Tensor) -> torch.Tensor:
        """lrelu -> IP2 -> scaled softplus on IP1's pre-activation."""
        z = self.ip2(self._lrelu(y)).squeeze(-1)
        return self.config.output_scale_m * F.softplus(z)

    def _ip1_packed(self, h: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 through oneDNN on cached weights, or None (`tiled_fusion.ip1_packed`)."""
        return tiled_fusion.ip1_packed(self, h)

    # Above this fraction of ambiguous IP1 inputs the dense product is cheaper (the split
    # costs two passes over the weights plus the per-candidate product on those inputs).
    _SPLIT_MAX_AMBIGUOUS = 0.6

    def _ip1_split(self, features: torch.Tensor, offsets: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 for K actions on one image, split by the sign of lrelu's argument, or
        None where that does not apply (`tiled_fusion.ip1_split`): (K, out)."""
        return tiled_fusion.ip1_split(self, features, offsets)

    # -- direct form -----------------------------------------------------------------

    def forward_direct(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """The paper's graph, literally: one image and one action per row.

        Args:
            images: Normalized depth, (B, 1, S, S).
            actions: (B, 3) raw or (B, 4) features.

        Returns:
            Distances [m], (B,), > 0.
        """
        self._check_images(images)
        feats = self._features(actions)
        if feats.ndim != 2 or feats.shape[0] != images.shape[0]:
            raise ValueError(
                f"actions: expected shape ({images.shape[0]}, 3 or 4) to match "
                f"{images.shape[0]} images, got {tuple(feats.shape)}"
            )
        if self.window:
            return self._window_scores(self.image_features(images), feats[:, None])[:, 0]
        if self.grid:
            return self._grid_scores(self.image_features(images), feats[:, None])[:, 0]
        x = F.max_pool2d(self._lrelu(self.conv1(images)), 2)
        x = x + self.ip_action(feats)[:, :, None, None]  # tiled over Pool1's H, W
        x = F.max_pool2d(self._lrelu(self.conv2(x)), 2)
        return self._head(x.flatten(1))

    def forward(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Same as `forward_direct`."""
        return self.forward_direct(images, actions)

    # -- factored (fast) form ----------------------------------------------------------

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """The action-independent part: pool2(Conv2(Pool1(lrelu(Conv1(I))))).

        Conv2's bias is included; Conv2's leaky ReLU is *not* (it comes after the
        action's per-channel shift, see the module docstring).

        Args:
            images: Normalized depth, (B, 1, S, S).

        Returns:
            (B, C2, P, P): (B, 50, 13, 13) for the defaults.
        """
        if self.grid:
            return self._after_ip1_grid(self.grid_hidden(images))
        self._check_images(images)
        x = F.max_pool2d(self._lrelu(self.conv1(images)), 2)
        if self.window:
            fmap = self._lrelu(self.conv2(x))
            ref = self._reference_depth(images)[:, None, None, None]
            return torch.cat((fmap, ref.expand(-1, 1, *fmap.shape[2:])), dim=1)
        return F.max_pool2d(self.conv2(x), 2)

    def action_offsets(self, actions: ArrayLike) -> torch.Tensor:
        """Per-channel Conv2-output shift c(a) caused by the tiled action input.

        ``c = S @ IP_a(f)`` with ``S[o, i] = sum over taps of W2[o, i]``, folded into one
        affine map 4 -> C2 (so K actions cost a (K, 4) @ (4, C2) product).

        Args:
            actions: (..., 3) raw or (..., 4) features.

        Returns:
            (..., C2).
        """
        return tiled_fusion.action_offsets(self, actions)

    # -- window fusion -----------------------------------------------------------------

    def _reference_depth(self, images: torch.Tensor) -> torch.Tensor:
        """Each image's median depth [m] (`window_fusion.reference_depth`), (B,)."""
        return window_fusion.reference_depth(self, images)

    def _window_grid(self, feats: torch.Tensor, ref: torch.Tensor,
                     side_m: Optional[float] = None) -> torch.Tensor:
        """grid_sample coordinates of every candidate's window
        (`window_fusion.window_grid`), (B, M * n, n, 2)."""
        return window_fusion.window_grid(self, feats, ref, side_m)

    def _window_scores(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (B, M) for M actions on each of B images from `image_features`
        (`window_fusion.window_scores`)."""
        return window_fusion.window_scores(self, features, feats)

    # -- grid head ---------------------------------------------------------------------

    def _grid_corners(self, feats: torch.Tensor) -> list:
        return grid_head.grid_corners(self.config, feats)

    def _grid_scores(self, grids: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return grid_head.grid_scores(self.config, grids, feats)

    def _after_ip1_grid(self, hidden: torch.Tensor) -> torch.Tensor:
        """The whole distance grid, (..., T, N, N), from `grid_hidden` (..., ip1)."""
        return grid_head.after_ip1_grid(self, hidden)

    def grid_hidden(self, images: torch.Tensor) -> torch.Tensor:
        """Grid head: the trunk up to IP2's input, lrelu(IP1(...)), (B, ip1). IP2 maps it
        to the distance at every grid node; `score_grid_nodes` evaluates only the nodes
        a set of actions needs."""
        return grid_head.grid_hidden(self, images)

    def score_grid_nodes(self, hidden: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for K actions on one image from `grid_hidden`, computing IP2 only at
        the grid nodes around them (the controller's candidates lie within a few cm and
        tens of degrees of the hand: about 1/20 of the 18 x 33 x 33 nodes; for more than
        1/32 as many actions as nodes, IP2 runs over the whole grid). Equal to
        `score_actions(image_features(...))` (same interpolation of the same node values;
        IP2's rows are the same dot products, so the values agree to float rounding).

        Args:
            hidden: (ip1,) or (1, ip1), `grid_hidden` of one image.
            actions: (K, 3) raw or (K, 4) features.

        Returns:
            Distances [m], (K,).
        """
        return grid_head.score_grid_nodes(self, hidden, actions)

    def _score_features(self, features: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """Distances from image features and per-channel action shifts broadcast against
        them (`tiled_fusion.score_features`)."""
        return tiled_fusion.score_features(self, features, offsets)

    def score_actions(self, features: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for K candidate actions on one image (control).

        Call under `torch.inference_mode()` in a controller: no autograd graph is
        kept and, for float32 on CPU, IP1 is split (`_ip1_split`): the inputs whose
        leaky ReLU branch is the same for all K candidates cost one pass over IP1's
        weights for all of them, and only the others go through the per-candidate
        product (about 2x faster for the controller's candidates on the machines
        measured). Where that does not apply, all K actions go through IP1 as one
        (K, 8450) @ (8450, 500) product on cached oneDNN weights. The result is
        differentiable when a gradient is wanted.

        Args:
            features: `image_features` of one image, (C2, P, P) or (1, C2, P, P).
            actions: (K, 3) raw or (K, 4) features.

        Returns:
            Distances [m], (K,).
        """
        expected = self.config.feature_shape()
        if features.ndim == 4 and features.shape[0] == 1:
            features = features[0]
        if tuple(features.shape) != expected:
            raise ValueError(
                f"features: expected shape {expected} or (1, *{expected}) "
                f"(image_features of one image), got {tuple(features.shape)}"
            )
        if self.window or self.grid:
            feats = self._features(actions)
            if feats.ndim != 2:
                raise ValueError(
                    f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}")
            scores = self._grid_scores if self.grid else self._window_scores
            return scores(features[None], feats[None])[0]
        offsets = self.action_offsets(actions)
        if offsets.ndim != 2:
            raise ValueError(
                f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}"
            )
        y = self._ip1_split(features, offsets)
        if y is None:
            return self._score_features(features[None], offsets)
        return self._after_ip1(y)

    def forward_factored(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for M actions on each of B images (training), differentiable.

        The image part runs once per image and is expanded over its M actions.

        Args:
            images: Normalized depth, (B, 1, S, S).
            actions: (B, M, 3) raw or (B, M, 4) features.

        Returns:
            Distances [m], (B, M).
        """
        features = self.image_features(images)
        if self.window or self.grid:
            feats = self._features(actions)
            if feats.ndim != 3 or feats.shape[0] != images.shape[0]:
                raise ValueError(
                    f"actions: expected shape ({images.shape[0]}, M, 3 or 4) to match "
                    f"{images.shape[0]} images, got {tuple(torch.as_tensor(actions).shape)}")
            scores = self._grid_scores if self.grid else self._window_scores
            return scores(features, feats)
        offsets = self.action_offsets(actions)
        if offsets.ndim != 3 or offsets.shape[0] != images.shape[0]:
            raise ValueError(
                f"actions: expected shape ({images.shape[0]}, M, 3 or 4) to match "
                f"{images.shape[0]} images, got {tuple(torch.as_tensor(actions).shape)}"
            )
        return self._score_features(features[:, None], offsets)
