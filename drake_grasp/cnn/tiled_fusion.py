"""The distance CNN's "tiled" head (the paper's fusion: IP_a(a) added to every Pool1
cell) and its exact factored fast path (`drake_grasp.cnn.network`'s docstring gives the
identities). This module owns `TiledHead`, the head `drake_grasp.cnn.network.DistanceCNN`
delegates to for it: the paper's direct graph after the shared trunk, the factored image
features (Pool2 of Conv2, before its lrelu), the per-channel Conv2 shift of an action
(`TiledHead.offsets`), the IP layers on them (`TiledHead.mlp`), and `InferenceIP1`, the
inference-only wrapper of IP1 with its two fast paths and their weight caches: IP1
through oneDNN on packed weights (`InferenceIP1.packed`, `_PackedWeights`) and IP1
split by the sign of lrelu's argument over K candidates (`InferenceIP1.split`,
`_SplitWeights`), both memoised per net (`weights_memo`).
"""

from typing import Optional

import torch
import torch.nn.functional as F


class _WeightsMemo:
    """A memo of something computed from parameters, for inference.

    Keyed on the parameters' storage and version counters, so an optimizer step,
    `load_state_dict` or a dtype/device move invalidates it. A pure cache of a function
    of the weights (results do not depend on whether it is warm); dropped on copy and
    pickle (oneDNN tensors are not copyable).
    """

    def __init__(self) -> None:
        self._key: Optional[tuple] = None
        self._value = None

    def _cached(self, tensors: tuple, make):
        """`make()`, recomputed when any of `tensors` changed; None where they have no
        version counter (inference tensors: no safe key, so no cache)."""
        try:
            key = tuple((t.data_ptr(), t._version) for t in tensors)
        except RuntimeError:
            return None
        if key != self._key:
            with torch.no_grad():
                self._value = make()
            self._key = key
        return self._value

    def __deepcopy__(self, memo: dict):
        return type(self)()

    def __reduce__(self):
        return (type(self), ())


class _PackedWeights(_WeightsMemo):
    """(weight, bias) converted to oneDNN tensors (`InferenceIP1.packed`)."""

    def __init__(self) -> None:
        super().__init__()
        # torch builds without oneDNN, or a failing conversion, use the default path.
        self._usable = torch.backends.mkldnn.is_available()

    def get(self, weight: torch.Tensor, bias: torch.Tensor):
        """The oneDNN (weight, bias) pair, or None if unavailable."""
        if not self._usable:
            return None
        try:
            return self._cached((weight, bias),
                                lambda: (weight.detach().to_mkldnn(), bias.detach().to_mkldnn()))
        except RuntimeError:
            self._usable = False
            return None


class _SplitWeights(_WeightsMemo):
    """IP1's weight in the two layouts `InferenceIP1.split` reads: ``by_channel``
    (C2, P*P, out) for the per-channel weighted sums in one batched product, and
    ``by_input`` (C2*P*P, out), whose rows are gathered for the ambiguous inputs."""

    def get(self, weight: torch.Tensor, channels: int):
        """(by_channel, by_input), or None where the weight has no version counter."""
        def make():
            by_input = weight.detach().t().contiguous()
            return by_input.reshape(channels, -1, weight.shape[0]).contiguous(), by_input

        return self._cached((weight,), make)


def weights_memo(net, kind: type):
    """The `DistanceCNN` `net`'s memo of class `kind` (`_PackedWeights`, `_SplitWeights`)."""
    # Created lazily so modules built by other means (e.g. deepcopy) get one too.
    key = f"_memo_{kind.__name__}"
    memo = net.__dict__.get(key)
    if memo is None:
        memo = net.__dict__[key] = kind()
    return memo


class InferenceIP1:
    """IP1 of the `DistanceCNN` `net` on its inference-only fast paths (no autograd):
    through oneDNN on cached packed weights (`packed`), and split by the sign of lrelu's
    argument over K candidates (`split`). Each returns None where it does not apply, and
    the caller then runs the plain layer. The weight caches live on the net
    (`weights_memo`), so this wrapper holds nothing of its own."""

    # Above this fraction of ambiguous IP1 inputs the dense product is cheaper (the split
    # costs two passes over the weights plus the per-candidate product on those inputs).
    SPLIT_MAX_AMBIGUOUS = 0.6

    def __init__(self, net) -> None:
        self.net = net

    def packed(self, h: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 through oneDNN with cached weights, or None where that does not apply.

        IP1 is the per-action floor. On the machines measured (AMD EPYC, torch's MKL
        build) oneDNN's fp32 GEMM runs this (K, 8450) @ (8450, 500) product about 2x
        faster than the default MKL path. It has no autograd, so it is used only when
        no gradient is wanted, for float32 on CPU. The result is the same float32
        product up to summation order (~1e-6 relative).
        """
        net = self.net
        w, b = net.ip1.weight, net.ip1.bias
        if (
            h.dtype != torch.float32
            or w.dtype != torch.float32
            or h.device.type != "cpu"
            or (torch.is_grad_enabled() and (h.requires_grad or w.requires_grad or b.requires_grad))
        ):
            return None
        packed = weights_memo(net, _PackedWeights).get(w, b)
        if packed is None:
            return None
        return F.linear(h.contiguous().to_mkldnn(), *packed).to_dense()

    def split(self, features: torch.Tensor, offsets: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 for K actions on one image, split by the sign of lrelu's argument.

        ``h_k[j, p] = lrelu(Z[j, p] + c_k[j])`` (Z: `image_features`, c_k:
        `action_offsets`). Where ``Z[j, p] + min_k c_k[j] > 0`` every candidate is on the
        identity branch; where ``Z[j, p] + max_k c_k[j] <= 0`` every candidate is on the
        ``slope`` branch. On both, ``h_k = s (Z + c_k)`` with s = 1 or slope, so their
        share of IP1 is ``W_s Z + M c_k`` with ``M[:, j] = sum_p s W[:, j, p]``: one
        pass over W for all K. The ambiguous inputs go through the per-candidate
        product. Returns None (use the dense product) where it does not apply: gradient
        wanted, not float32 on CPU, no candidates, or too many ambiguous inputs.

        Args:
            features: (C2, P, P) of one image.
            offsets: (K, C2).

        Returns:
            IP1's pre-activation, (K, out).
        """
        net = self.net
        w, b = net.ip1.weight, net.ip1.bias
        if (
            features.dtype != torch.float32
            or w.dtype != torch.float32
            or features.device.type != "cpu"
            or (torch.is_grad_enabled()
                and (features.requires_grad or offsets.requires_grad or w.requires_grad))
            or offsets.shape[0] == 0
        ):
            return None
        channels = features.shape[0]
        z = features.reshape(channels, -1)  # (C2, P*P)
        lo = offsets.min(dim=0).values[:, None]
        hi = offsets.max(dim=0).values[:, None]
        on = z + lo > 0
        off = z + hi <= 0
        ambiguous = (~(on | off)).reshape(-1).nonzero().squeeze(1)
        if ambiguous.numel() > self.SPLIT_MAX_AMBIGUOUS * z.numel():
            return None
        layouts = weights_memo(net, _SplitWeights).get(w, channels)
        if layouts is None:
            return None
        by_channel, by_input = layouts
        slope = net.config.leaky_slope
        s = torch.where(on, 1.0, torch.where(off, slope, 0.0)).to(z.dtype)
        # One batched pass over W: row 0 gives sum_p s Z W[:, j, p], row 1 gives M[:, j].
        sums = torch.bmm(torch.stack((s * z, s), dim=1), by_channel)  # (C2, 2, out)
        y = b + sums[:, 0].sum(dim=0) + offsets @ sums[:, 1]
        if ambiguous.numel():
            h = F.leaky_relu(z.reshape(-1)[ambiguous] + offsets[:, ambiguous // z.shape[1]], slope)
            y = y + h @ by_input.index_select(0, ambiguous)
        return y


class TiledHead:
    """The paper's head on the `DistanceCNN` `net`'s shared trunk: IP_a(a) tiled over
    Pool1, then Conv2 -> lrelu -> pool2 -> IP1 -> lrelu -> IP2 -> scaled softplus. The
    factored form computes Pool2 of Conv2 once per image (`image_features`) and adds
    each action's per-channel shift (`offsets`) after it. Holds only the net (whose
    layers it reads) and is made afresh by `DistanceCNN.head`."""

    def __init__(self, net) -> None:
        self.net = net
        self.fast_ip1 = InferenceIP1(net)

    def direct(self, images: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """The paper's graph, literally: (B,) distances for (B, 4) action features."""
        net = self.net
        x = net.trunk(images)
        x = x + net.ip_action(feats)[:, :, None, None]  # tiled over Pool1's H, W
        x = F.max_pool2d(net._lrelu(net.conv2(x)), 2)
        return self.mlp(x.flatten(1))

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """pool2(Conv2(Pool1)), Conv2's bias included and its lrelu not, (B, C2, P, P)."""
        return F.max_pool2d(self.net.conv2(self.net.trunk(images)), 2)

    def offsets(self, feats: torch.Tensor) -> torch.Tensor:
        """The per-channel Conv2-output shift of each action's features, (..., C2):
        ``S @ IP_a(f)`` with ``S[o, i] = sum over taps of W2[o, i]``, folded into one
        affine map 4 -> C2."""
        net = self.net
        tap_sums = net.conv2.weight.sum(dim=(2, 3))  # (C2, C1)
        weight = tap_sums @ net.ip_action.weight  # (C2, 4)
        bias = tap_sums @ net.ip_action.bias  # (C2,)
        return F.linear(feats, weight, bias)

    def mlp(self, h: torch.Tensor, *, fast_ip1: bool = False) -> torch.Tensor:
        """IP1 -> lrelu -> IP2 -> scaled softplus on flattened Pool2 activations; IP1 on
        `InferenceIP1.packed` where `fast_ip1` and that applies."""
        y = self.fast_ip1.packed(h) if fast_ip1 else None
        if y is None:
            y = self.net.ip1(h)
        return self.net._after_ip1(y)

    def score_features(self, features: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """Distances from image features (..., C2, P, P) and per-channel action shifts
        (..., C2) broadcast against them."""
        # features (..., C2, P, P) broadcast against offsets (..., C2): one row of IP1
        # input per action, then the head as a single (N, 8450) @ (8450, 500) product.
        h = self.net._lrelu(features + offsets[..., None, None])
        lead = h.shape[:-3]
        out = self.mlp(h.reshape(-1, self.net.config.num_features), fast_ip1=True)
        return out.reshape(lead)

    def scores(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (B, M) for M actions' features (B, M, 4) on each of B images from
        `image_features` (B, C2, P, P)."""
        return self.score_features(features[:, None], self.offsets(feats))

    def score_one(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances (K,) for K actions' features (K, 4) on one image's features
        (C2, P, P): IP1 split over the candidates (`InferenceIP1.split`) where that
        applies, else the dense product."""
        offsets = self.offsets(feats)
        y = self.fast_ip1.split(features, offsets)
        if y is None:
            return self.score_features(features[None], offsets)
        return self.net._after_ip1(y)
