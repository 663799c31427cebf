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
(`tiled_fusion.InferenceIP1.split`). IP1's input is ``lrelu(Zp[j, p] + c_k[j])``; an
input whose argument has the same sign for all K candidates (``Zp[j, p] + min_k c_k[j]
> 0``, or ``Zp[j, p] + max_k c_k[j] <= 0``) is affine in c_k, so its share of IP1 is one
matrix-vector pass over the weights for all K together. Only the remaining inputs
(about 20-30% on the wrist images measured) go through the per-candidate product.
Same numbers up to summation order.

This module owns the model: its layers (their attribute names are the weights files'
tensor names), the shared trunk (`DistanceCNN.trunk`: Conv1 -> lrelu -> Pool1) and the
public forms above, which check their inputs and delegate to the head of the net's
action fusion (`DistanceCNN.head`): `tiled_fusion.TiledHead` (the paper's, with the
inference-only IP1 paths `tiled_fusion.InferenceIP1`), `window_fusion.WindowHead` or
`grid_head.GridHead`. A head holds no weights of its own: it reads the net's layers, so
the state_dict keys are the layers' attribute names here whatever the fusion. The
config and input encoding are `drake_grasp.cnn.net_config`'s; test-time mirror
averaging is `drake_grasp.cnn.mirror`'s and weights I/O (safetensors only, verified on
load) `drake_grasp.cnn.weights_io`'s. It knows nothing of Drake; `drake_grasp.systems`
wraps it.
"""

# No `from __future__ import annotations`: NetworkConfig may be nested in scenario
# dataclasses read by Drake's yaml_load_typed, which needs real annotation objects.

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from drake_grasp.cnn.grid_head import GridHead
from drake_grasp.cnn.net_config import ArrayLike, NetworkConfig, action_features, normalize_depth
from drake_grasp.cnn.tiled_fusion import TiledHead
from drake_grasp.cnn.window_fusion import WindowHead

# The head of each `NetworkConfig.action_fusion`.
_HEADS = {"tiled": TiledHead, "window": WindowHead, "grid": GridHead}


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

    @property
    def head(self):
        """The head of this net's action fusion on its layers (`TiledHead`, `WindowHead`
        or `GridHead`). Made on each access: it holds nothing but the net, so copies of
        the net (deep or shallow) each get their own."""
        return _HEADS[self.config.action_fusion](self)

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

    def _after_ip1(self, y: torch.Tensor) -> torch.Tensor:
        """lrelu -> IP2 -> scaled softplus on IP1's pre-activation (tiled and window)."""
        z = self.ip2(self._lrelu(y)).squeeze(-1)
        return self.config.output_scale_m * F.softplus(z)

    # -- the shared trunk ----------------------------------------------------------------

    def trunk(self, images: torch.Tensor) -> torch.Tensor:
        """Pool1 of normalized images: Conv1 -> lrelu -> 2x2 max-pool, (B, C1, 30, 30) for
        the defaults. Every head goes on to Conv2 from here (the tiled one after adding
        the action)."""
        return F.max_pool2d(self._lrelu(self.conv1(images)), 2)

    # -- the forms, each delegating to the head ----------------------------------------

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
        return self.head.direct(images, feats)

    def forward(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Same as `forward_direct`."""
        return self.forward_direct(images, actions)

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """The action-independent part of each image, computed once for all its actions.

        Tiled (the paper's): pool2(Conv2(Pool1(lrelu(Conv1(I))))), Conv2's bias included
        and its leaky ReLU *not* (it comes after the action's per-channel shift, see the
        module docstring): (B, C2, P, P), (B, 50, 13, 13) for the defaults. Window:
        lrelu(Conv2) unpooled and the reference depth, (B, C2 + 1, S, S). Grid: the
        whole distance grid, (B, T, N, N).

        Args:
            images: Normalized depth, (B, 1, S, S).
        """
        self._check_images(images)
        return self.head.image_features(images)

    def action_offsets(self, actions: ArrayLike) -> torch.Tensor:
        """Per-channel Conv2-output shift c(a) caused by the tiled action input.

        ``c = S @ IP_a(f)`` with ``S[o, i] = sum over taps of W2[o, i]``, folded into one
        affine map 4 -> C2 (so K actions cost a (K, 4) @ (4, C2) product).

        Args:
            actions: (..., 3) raw or (..., 4) features.

        Returns:
            (..., C2).
        """
        if self.window or self.grid:
            raise ValueError(f"action_offsets: a {self.config.action_fusion!r} net has no "
                             "per-channel action shift")
        return TiledHead(self).offsets(self._features(actions))

    def score_actions(self, features: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for K candidate actions on one image (control).

        Call under `torch.inference_mode()` in a controller: no autograd graph is
        kept and, for a tiled net in float32 on CPU, IP1 is split
        (`tiled_fusion.InferenceIP1.split`): the inputs whose leaky ReLU branch is the
        same for all K candidates cost one pass over IP1's weights for all of them, and
        only the others go through the per-candidate product (about 2x faster for the
        controller's candidates on the machines measured). Where that does not apply,
        all K actions go through IP1 as one (K, 8450) @ (8450, 500) product on cached
        oneDNN weights. The result is differentiable when a gradient is wanted.

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
        feats = self._features(actions)
        if feats.ndim != 2:
            raise ValueError(
                f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}")
        return self.head.score_one(features, feats)

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
        feats = self._features(actions)
        if feats.ndim != 3 or feats.shape[0] != images.shape[0]:
            raise ValueError(
                f"actions: expected shape ({images.shape[0]}, M, 3 or 4) to match "
                f"{images.shape[0]} images, got {tuple(torch.as_tensor(actions).shape)}")
        return self.head.scores(features, feats)

    # -- the grid head's control path --------------------------------------------------

    def grid_hidden(self, images: torch.Tensor) -> torch.Tensor:
        """Grid head: the trunk up to IP2's input, lrelu(IP1(...)), (B, ip1). IP2 maps it
        to the distance at every grid node; `score_grid_nodes` evaluates only the nodes
        a set of actions needs."""
        self._check_images(images)
        if not self.grid:
            raise ValueError(f"grid_hidden: a {self.config.action_fusion!r} net has no grid head")
        return GridHead(self).hidden(images)

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
        if hidden.ndim == 2 and hidden.shape[0] == 1:
            hidden = hidden[0]
        if tuple(hidden.shape) != (self.config.ip1,):
            raise ValueError(f"hidden: expected shape ({self.config.ip1},) or (1, "
                             f"{self.config.ip1}) (grid_hidden of one image), got "
                             f"{tuple(hidden.shape)}")
        feats = self._features(actions)
        if feats.ndim != 2:
            raise ValueError(
                f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}")
        return GridHead(self).score_nodes(hidden, feats)
