"""The distance CNN's "tiled" fusion (the paper's: IP_a(a) added to every Pool1 cell) and
its exact factored fast path (`drake_grasp.cnn.network`'s docstring gives the
identities). This module owns what `drake_grasp.cnn.network.DistanceCNN` delegates to
for it: the per-channel Conv2 shift of an action (`action_offsets`), the scores of
actions from an image's features (`score_features`), and the two inference-only IP1
paths with their weight caches: IP1 through oneDNN on packed weights (`ip1_packed`,
`_PackedWeights`) and IP1 split by the sign of lrelu's argument over K candidates
(`ip1_split`, `_SplitWeights`), both memoised per net (`weights_memo`).
"""

from typing import Optional

import torch
import torch.nn.functional as F

from drake_grasp.cnn.net_config import ArrayLike


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
    """(weight, bias) converted to oneDNN tensors (`DistanceCNN._ip1_packed`)."""

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
    """IP1's weight in the two layouts `DistanceCNN._ip1_split` reads: ``by_channel``
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


def ip1_packed(net, h: torch.Tensor) -> Optional[torch.Tensor]:
    """IP1 through oneDNN with cached weights, or None where that does not apply.

    IP1 is the per-action floor. On the machines measured (AMD EPYC, torch's MKL
    build) oneDNN's fp32 GEMM runs this (K, 8450) @ (8450, 500) product about 2x
    faster than the default MKL path. It has no autograd, so it is used only when
    no gradient is wanted, for float32 on CPU. The result is the same float32
    product up to summation order (~1e-6 relative).
    """
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


def ip1_split(net, features: torch.Tensor, offsets: torch.Tensor) -> Optional[torch.Tensor]:
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
    if ambiguous.numel() > net._SPLIT_MAX_AMBIGUOUS * z.numel():
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


def action_offsets(net, actions: ArrayLike) -> torch.Tensor:
    """`DistanceCNN.action_offsets` of `net`: the per-channel Conv2-output shift of each
    action, (..., C2)."""
    if net.window or net.grid:
        raise ValueError(f"action_offsets: a {net.config.action_fusion!r} net has no "
                         "per-channel action shift")
    feats = net._features(actions)
    tap_sums = net.conv2.weight.sum(dim=(2, 3))  # (C2, C1)
    weight = tap_sums @ net.ip_action.weight  # (C2, 4)
    bias = tap_sums @ net.ip_action.bias  # (C2,)
    return F.linear(feats, weight, bias)


def score_features(net, features: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Distances of the `DistanceCNN` `net` from image features (..., C2, P, P) and
    per-channel action shifts (..., C2) broadcast against them."""
    # features (..., C2, P, P) broadcast against offsets (..., C2): one row of IP1
    # input per action, then the head as a single (N, 8450) @ (8450, 500) product.
    h = net._lrelu(features + offsets[..., None, None])
    lead = h.shape[:-3]
    out = net._head(h.reshape(-1, net.config.num_features), fast_ip1=True)
    return out.reshape(lead)
