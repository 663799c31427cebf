"""The distance CNN's mirror symmetry, for test-time averaging: the wrist camera, the
gripper and physics are all symmetric in the hand's y-z plane, so d(flip(I), mirror(a))
= d(I, a). This module owns the two halves of that map, `mirror_actions` (actions or
their features reflected) and `mirror_images` (depth images flipped left-right), and
`MirrorAveragedCNN`, a `drake_grasp.cnn.network.DistanceCNN` wrapper whose every
distance is the mean over the image and its mirror image.
"""

import numpy as np
import torch
from torch import nn

from drake_grasp.cnn.net_config import ArrayLike
from drake_grasp.cnn.network import DistanceCNN


def mirror_actions(actions: ArrayLike) -> ArrayLike:
    """Actions reflected in the hand's y-z plane: (x, y, theta) -> (-x, y, -theta);
    features [x/s, y/s, cos 2theta, sin 2theta] -> [-x/s, y/s, cos 2theta, -sin 2theta].

    The wrist camera sits on that plane (`X_GC` = (0, -0.05, -0.115), axes along the
    grasp frame's), the 2F-85's fingers are mirror images across it, and gravity and
    friction do not care, so the distance to the nearest grasp of a mirrored scene, seen
    in the image flipped left-right (`mirror_images`), for the mirrored action, is the
    distance of the original: d(flip(I), mirror(a)) = d(I, a).
    """
    a = actions.clone() if isinstance(actions, torch.Tensor) else np.array(actions, copy=True)
    if a.shape[-1] not in (3, 4):
        raise ValueError(f"actions: expected last dimension 3 or 4, got shape {tuple(a.shape)}")
    a[..., 0] = -a[..., 0]
    a[..., a.shape[-1] - 1] = -a[..., a.shape[-1] - 1]
    return a


def mirror_images(images: ArrayLike) -> ArrayLike:
    """Depth images flipped left-right (the last axis: image columns, the camera's x)."""
    if isinstance(images, torch.Tensor):
        return images.flip(-1)
    return np.ascontiguousarray(np.asarray(images)[..., ::-1])


class MirrorAveragedCNN(nn.Module):
    """A `DistanceCNN` whose every distance is the mean of d(I, a) and
    d(flip(I), mirror(a)) (`mirror_actions`): test-time averaging over the one symmetry
    that the wrist camera, the gripper and physics share. The same interface as the
    network it wraps (`preprocess`, `image_features`, `score_actions`, `forward`,
    `forward_factored`), twice its cost; no weights of its own.

    `image_features` returns both images' features, (B, 2, C2, P, P); `score_actions`
    takes them for one image ((2, C2, P, P) or (1, 2, C2, P, P)).
    """

    def __init__(self, base: "DistanceCNN") -> None:
        super().__init__()
        if isinstance(base, MirrorAveragedCNN):
            raise ValueError("base: already mirror-averaged")
        self.base = base
        self.config = base.config

    @property
    def dtype(self) -> torch.dtype:
        return self.base.dtype

    def preprocess(self, depth: ArrayLike) -> torch.Tensor:
        return self.base.preprocess(depth)

    def forward(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        return 0.5 * (self.base.forward(images, actions)
                      + self.base.forward(mirror_images(images), mirror_actions(actions)))

    def forward_factored(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        return 0.5 * (self.base.forward_factored(images, actions)
                      + self.base.forward_factored(mirror_images(images), mirror_actions(actions)))

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        return torch.stack((self.base.image_features(images),
                            self.base.image_features(mirror_images(images))), dim=1)

    def score_actions(self, features: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        if features.ndim == 5 and features.shape[0] == 1:
            features = features[0]
        if features.ndim != 4 or features.shape[0] != 2:
            raise ValueError(
                "features: expected MirrorAveragedCNN.image_features of one image, "
                f"(2, C2, P, P) or (1, 2, C2, P, P), got {tuple(features.shape)}")
        return 0.5 * (self.base.score_actions(features[0], actions)
                      + self.base.score_actions(features[1], mirror_actions(actions)))
