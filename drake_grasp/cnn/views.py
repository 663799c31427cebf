"""The wrist image's symmetric views, and a grid net's distances averaged over them.

Training augments with these views (`drake_grasp.learning.dense_training`); the controller
may average a grid net's distances over them at test time (`controller.view_average`).
"""

from __future__ import annotations

import numpy as np
import torch

from drake_grasp.cnn.network import DistanceCNN


# The wrist camera looks straight down along z_G, so turning the hand about the camera's
# axis turns the image about its optical axis, and reflecting the scene in the camera's
# y-z plane flips it left-right: the dihedral group of the square ("D4": 4 turns by 90
# degrees, each with or without the flip). The labels follow exactly, because a label is
# a distance between planar poses and the scene's grasps turn (or reflect) with it
# (gravity and the 2F-85 are symmetric).
AUGMENTATIONS = {"none": ((0, False),),
                 "mirror": ((0, False), (0, True)),
                 "d4": tuple((k, f) for f in (False, True) for k in range(4))}


def optical_axis_px(size: int) -> int:
    """The pixel row (column) of the optical axis in Drake's rendered images of an even
    `size`: size / 2 - 1, half a pixel from `CameraInfo`'s documented principal point
    (size / 2 - 0.5). Measured (`tests/test_dense_training.py`): the 64-pixel wrist image
    rendered from a hand turned 90, 180 or 270 degrees about the camera's axis is the
    image turned about pixel 31, and GPD's 640 x 480 image turned 180 degrees about
    (319, 239)."""
    if size < 2 or size % 2:
        raise ValueError(f"optical_axis_px: measured for even image sizes, got {size}")
    return size // 2 - 1


def turn_images(depth: np.ndarray, k: int, flip: bool) -> np.ndarray:
    """Depth images (..., H, H) as seen after the symmetry (k quarter turns, `np.rot90`'s
    sense on (rows, columns), after a left-right flip when `flip`) about the optical axis
    (`optical_axis_px`). The last row and column have no partner inside the image; they
    repeat their neighbours."""
    depth = np.asarray(depth)
    h, w = depth.shape[-2:]
    if h != w:
        raise ValueError(f"turn_images: expected square images, got {h} x {w}")
    side = 2 * optical_axis_px(h) + 1
    if k % 4 == 0 and not flip:
        return depth.copy()
    core = depth[..., :side, :side]
    if flip:
        core = core[..., ::-1]
    core = np.rot90(core, k, axes=(-2, -1))
    pad = [(0, 0)] * (depth.ndim - 2) + [(0, h - side), (0, w - side)]
    return np.ascontiguousarray(np.pad(core, pad, mode="edge"))


def turn_grids(grid: np.ndarray, k: int, flip: bool) -> np.ndarray:
    """Label grids (..., T, N, N) (theta, y, x, as the grid head's output) under the
    symmetry that `turn_images(images, k, flip)` applies to their images: the same turn of
    the (y, x) nodes about the camera's centre, theta -> -theta for the flip, and +90
    degrees for an odd number of quarter turns."""
    grid = np.asarray(grid)
    t_bins = grid.shape[-3]
    if k % 2 and t_bins % 2:
        raise ValueError(f"turn_grids: a quarter turn needs theta bins that hold 90 degrees, "
                         f"got {t_bins} bins over 180")
    out = grid[..., ::-1] if flip else grid
    out = np.rot90(out, k, axes=(-2, -1))
    t = np.arange(t_bins)
    src = (-t if flip else t) + (k % 2) * (t_bins // 2)  # output bin of input bin t
    turned = np.empty_like(out)
    turned[..., src % t_bins, :, :] = out
    return turned


def view_averaged_grids(net: DistanceCNN, images: torch.Tensor, views: str, *,
                        batch_images: int = 256) -> torch.Tensor:
    """A grid-head net's distance grids (B, T, N, N) of normalized images (B, 1, S, S),
    each the mean over the image's symmetric views (`AUGMENTATIONS[views]`: "mirror" 2,
    "d4" 8; `turn_images` about the optical axis) of the view's grid turned back to the
    image as shown (the inverse of `turn_grids`). "none": the net's own grids. The views
    of up to `batch_images` images go through the trunk as one batch (one image's 8
    views in a controller step)."""
    if views not in AUGMENTATIONS:
        raise ValueError(f"views: expected one of {sorted(AUGMENTATIONS)}, got {views!r}")
    if not getattr(net, "grid", False):
        raise ValueError(f"views {views!r}: needs a grid-head net (the whole grid turns with "
                         f"the view), got a {net.config.action_fusion!r} net")
    ops = AUGMENTATIONS[views]
    if len(ops) == 1:
        return net.image_features(images)
    back = _views_back(net.config.grid_shape(), views)
    shown = images.detach().cpu().numpy()  # once, not per view
    per_call = max(1, int(batch_images) // len(ops))
    out = []
    for start in range(0, len(shown), per_call):
        part = shown[start:start + per_call]
        turned = np.concatenate([turn_images(part, k, flip) for k, flip in ops])
        grids = net.image_features(torch.from_numpy(turned).to(images.dtype))
        grids = grids.reshape(len(ops), len(part), -1)
        mean = sum(grids[v][:, inverse] for v, inverse in enumerate(back)) / len(ops)
        out.append(mean.reshape(len(part), *net.config.grid_shape()))
    return torch.cat(out)


_VIEWS_BACK: dict = {}


def _views_back(shape: tuple, views: str) -> list:
    """Per view of `AUGMENTATIONS[views]`, the index that turns a flattened grid of that
    view back to the image as shown: turned[i] = grid[p[i]] (`turn_grids`), so the view's
    grid at p^-1 is the shown image's grid."""
    key = (tuple(shape), views)
    if key not in _VIEWS_BACK:
        index = np.arange(int(np.prod(shape))).reshape(shape)
        back = []
        for k, flip in AUGMENTATIONS[views]:
            p = turn_grids(index, k, flip).ravel()
            inverse = np.empty_like(p)
            inverse[p] = np.arange(len(p))
            back.append(torch.from_numpy(inverse))
        _VIEWS_BACK[key] = back
    return _VIEWS_BACK[key]
