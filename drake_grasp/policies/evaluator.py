"""The learned distance function and the candidate sampler as LeafSystems.

The CNN runs on one of two backends, chosen by the weights file (`load_cnn`): torch for
a ``*.safetensors`` file (`drake_grasp.cnn.network`; the height-map FCN's, `drake_grasp.cnn.fcn`,
told apart by its metadata), onnxruntime for an ``X.onnx`` file from
``drake-grasp export-onnx`` (`drake_grasp.cnn.onnx_runtime`). torch is imported only by the
torch backend, so this module and the ONNX backend run where torch is not installed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Union

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem, NumericParameterIndex
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.core.assets import models_dir
from drake_grasp.cnn.onnx_runtime import OnnxDistanceModel
from drake_grasp.policies.decisions import sample_candidates

if TYPE_CHECKING:
    from drake_grasp.cnn.fcn import FcnDistanceModel
    from drake_grasp.cnn.network import DistanceCNN

# The default distance CNN: the paper's trunk with the grid head, trained with BatchNorm
# (folded into its layers), last on the paper's 12,500 scenes for 3 epochs
# (models/cnn-grid-bn12500-ep3/README.md: BN12500_WEIGHTS trained one epoch more; against
# it on fresh seeds, clutter and clutter-shift pooled 262/287 vs 241/278, isolation 117 vs
# 117 of 120: the rule of analysis/results/bn-paper-scale-ep3/PLAN.md), its weights stored
# in float16 and computed in float32 (models/cnn-grid-bn12500-ep3-fp16/README.md; no
# headline cell worse than with EP3_FLOAT32_WEIGHTS: analysis/results/fp16-default/).
# EP3_FLOAT32_WEIGHTS (the same net in float32, the default until 2026-12-08),
# BN12500_WEIGHTS (2 epochs on 12,500 scenes), EP5_WEIGHTS (5 epochs on 7,500 scenes),
# BN12_WEIGHTS (2 epochs on those scenes), BN_WEIGHTS (on 2,500 scenes), the grid head
# trained without BatchNorm (GRID_WEIGHTS) and the paper's tiled net (PAPER_WEIGHTS) stay
# in the repository's models/ and selectable (the wheel carries the default only,
# `core.assets.SHIPPED_MODELS`); records made with an earlier default replay with it
# (`replay.recorded_weights`).
DEFAULT_WEIGHTS = "cnn-grid-bn12500-ep3-fp16/weights.safetensors"
EP3_FLOAT32_WEIGHTS = "cnn-grid-bn12500-ep3/weights.safetensors"
BN12500_WEIGHTS = "cnn-grid-bn12500/weights.safetensors"
EP5_WEIGHTS = "cnn-grid-bn12-ep5/weights.safetensors"
BN12_WEIGHTS = "cnn-grid-bn12/weights.safetensors"
BN_WEIGHTS = "cnn-grid-bn/weights.safetensors"
GRID_WEIGHTS = "cnn-grid/weights.safetensors"
PAPER_WEIGHTS = "cnn/weights.safetensors"
# The height-map FCN with its grasp head (drake_grasp/cnn/fcn.py; models/fcn-heightmap/README.md):
# not the default; it needs the camera's height, the controller's `camera_height` port.
FCN_WEIGHTS = "fcn-heightmap/weights.safetensors"


class CnnEnsemble:
    """Several distance CNNs scored as one: a candidate's distance is the mean of the
    members' (`score_candidates`). Members may mix backends and heads (a tiled paper net,
    a grid head, an ONNX file); each costs its own pass per image. `load_cnn` builds one
    from a comma-separated list of weights files (``controller.weights: A,B``)."""

    def __init__(self, members) -> None:
        self.members = tuple(members)
        if len(self.members) < 2:
            raise ValueError(f"CnnEnsemble: expected at least 2 members, got {len(self.members)}")
        if any(isinstance(m, CnnEnsemble) for m in self.members):
            raise ValueError("CnnEnsemble: a member is itself an ensemble (list its files instead)")


def weights_files(weights: str) -> list[str]:
    """The weights files a `controller.weights` value names: "" -> [the shipped default];
    "A,B" -> [A, B] (an ensemble, `CnnEnsemble`). Raises ValueError on an empty item."""
    if not weights:
        return [str(models_dir() / DEFAULT_WEIGHTS)]
    parts = [p.strip() for p in str(weights).split(",")]
    if len(parts) > 1 and not all(parts):
        raise ValueError(f"controller.weights: {weights!r} has an empty item; expected "
                         "FILE or FILE,FILE,... (an ensemble)")
    return parts


def needs_torch(weights: str) -> bool:
    """Whether `load_cnn(weights)` loads any torch member (not all of them ONNX files)."""
    return not all(f.endswith(".onnx") for f in weights_files(weights))


def load_cnn(weights: str = "", *, threads: int = 1
             ) -> Union[DistanceCNN, OnnxDistanceModel, CnnEnsemble]:
    """The distance CNN from a weights file; "" -> the shipped default, `DEFAULT_WEIGHTS`
    under `models/` (the earlier shipped nets are the other `*_WEIGHTS` constants above).
    Several files separated by commas load a `CnnEnsemble` of them (the mean distance).

    A path ending in ``.onnx`` (the image file of ``drake-grasp export-onnx``, its
    ``.head.onnx`` sibling beside it) loads the onnxruntime backend
    (`OnnxDistanceModel` with `threads` intra-op threads: `controller.torch_threads` in an
    episode); anything else is a safetensors file for torch (whose threads the episode
    sets process-wide): a `DistanceCNN`'s, or the height-map FCN's (`fcn.FCN_FORMAT` in
    its metadata, `FCN_WEIGHTS`; scored with the camera's height, `needs_camera_height`).
    """
    files = weights_files(weights)
    if len(files) > 1:
        return CnnEnsemble(load_cnn(f, threads=threads) for f in files)
    path = files[0]
    if str(path).endswith(".onnx"):
        return OnnxDistanceModel(path, threads=max(1, int(threads)))
    from drake_grasp.cnn.fcn import FCN_FORMAT, load_fcn, weights_format

    if weights_format(path) == FCN_FORMAT:
        return load_fcn(path)[0]
    from drake_grasp.cnn.weights_io import load_weights

    model, _ = load_weights(path)
    return model.eval()


def needs_camera_height(model) -> bool:
    """Whether `score_candidates(model, ...)` needs `camera_height_m` (an FCN, or an
    ensemble with one)."""
    if isinstance(model, CnnEnsemble):
        return any(needs_camera_height(m) for m in model.members)
    return bool(getattr(model, "needs_camera_height", False))


def score_candidates(model: Union[DistanceCNN, OnnxDistanceModel, CnnEnsemble, FcnDistanceModel],
                     depth: np.ndarray, actions: np.ndarray, *, mirror: bool = False,
                     views: str = "none", camera_height_m: float | None = None) -> np.ndarray:
    """Predicted distance [m] for each candidate action on one depth image (fast path).

    `mirror`: the mean of the scores on the image and on its mirror image with the
    mirrored actions (`mirror.mirror_actions`; `controller.mirror_average`).
    `views` ("mirror" or "d4"; `controller.view_average`): a grid-head torch net's whole
    distance grid averaged over the image's symmetric views about the optical axis, each
    view's grid turned back (`dense_training.view_averaged_grids`), then interpolated at
    the actions; 2 or 8 trunk passes.
    A `CnnEnsemble`: the mean of its members' scores. `camera_height_m`: the camera's
    height above the table when the image was taken, which the height-map FCN needs
    (`needs_camera_height`; the CNNs ignore it)."""
    if isinstance(model, CnnEnsemble):
        return np.mean([score_candidates(m, depth, actions, mirror=mirror, views=views,
                                         camera_height_m=camera_height_m)
                        for m in model.members], axis=0)
    if views != "none":
        return _score_view_averaged(model, depth, actions, mirror=mirror, views=views)
    if mirror:
        from drake_grasp.cnn.mirror import mirror_actions, mirror_images

        return 0.5 * (score_candidates(model, depth, actions, camera_height_m=camera_height_m)
                      + score_candidates(model, mirror_images(np.asarray(depth)),
                                         mirror_actions(np.asarray(actions)),
                                         camera_height_m=camera_height_m))
    if needs_camera_height(model):
        if camera_height_m is None:
            raise ValueError(f"{getattr(model, 'path', '') or 'the height-map FCN'}: scoring "
                             "needs camera_height_m (the camera's height above the table)")
        return model.score(depth, actions, camera_height_m)
    if isinstance(model, OnnxDistanceModel):
        return model.score(depth, np.asarray(actions, np.float32))
    import torch

    with torch.inference_mode():
        images = model.preprocess(np.array(depth, np.float32))
        if model.grid:  # IP2 only at the grid nodes the candidates need
            hidden = model.grid_hidden(images)
            scores = model.score_grid_nodes(hidden, np.asarray(actions, np.float32))
            return scores.numpy().astype(float)
        features = model.image_features(images)
        return model.score_actions(features[0], np.asarray(actions, np.float32)).numpy().astype(float)


def check_views(model, views: str, *, mirror: bool = False) -> None:
    """Raises ValueError unless `score_candidates(model, ..., mirror=mirror, views=views)`
    can score: views "none", or "mirror" / "d4" on grid-head torch nets (every member of an
    ensemble) without `mirror`. An episode checks this when it is built, before the first
    decision."""
    if views == "none":
        return
    if mirror:
        raise ValueError("controller.mirror_average and controller.view_average: choose one "
                         "(view_average: mirror averages over the mirror image about the "
                         "optical axis)")
    for m in (model.members if isinstance(model, CnnEnsemble) else (model,)):
        if isinstance(m, OnnxDistanceModel) or needs_camera_height(m) or not getattr(
                m, "grid", False):
            label = getattr(m, "path", "") or type(m).__name__
            raise ValueError(f"controller.view_average {views!r}: needs a grid-head torch net "
                             f"(the whole distance grid turns with the view), got {label}")


def _score_view_averaged(model, depth: np.ndarray, actions: np.ndarray, *, mirror: bool,
                         views: str) -> np.ndarray:
    """`score_candidates(..., views=views)` for one grid-head torch net."""
    check_views(model, views, mirror=mirror)
    import torch

    from drake_grasp.cnn.views import view_averaged_grids
    from drake_grasp.cnn.grid_head import grid_scores
    from drake_grasp.cnn.net_config import action_features

    with torch.inference_mode():
        images = model.preprocess(np.array(depth, np.float32))
        grids = view_averaged_grids(model, images, views)
        feats = action_features(np.asarray(actions, np.float32), model.config, dtype=model.dtype)
        return grid_scores(model.config, grids, feats[None])[0].numpy().astype(float)


class DistanceEvaluator(LeafSystem):
    """d(I, a): the CNN's predicted distance to the nearest grasp for each candidate.

    Input ports:
        depth_image: post-processed wrist depth (ImageDepth32F).
        candidate_actions: (K, 3) actions [dx, dy, dtheta_deg] in the hand frame.
        camera_height (only for a model that needs it, `needs_camera_height`: the
            height-map FCN): (1,) the camera's height above the table [m] where the
            image was taken, the controller's belief (`GraspController`'s port).
    Output ports:
        predicted_distances: (K,) metres.
    """

    def __init__(self, model: Union[DistanceCNN, OnnxDistanceModel, CnnEnsemble, FcnDistanceModel],
                 *, score_fn=None, mirror: bool = False, views: str = "none"):
        """`model`: from `load_cnn` (torch or onnxruntime backend). `score_fn(depth,
        actions)` (with `camera_height_m=` for a model that needs it) replaces
        `score_candidates(model, ..., mirror=mirror, views=views)` (e.g. a timed wrapper
        of it)."""
        super().__init__()
        if score_fn is None:
            check_views(model, views, mirror=mirror)
        self._model = model
        self._needs_height = needs_camera_height(model)
        self._score_fn = score_fn or (lambda depth, actions, **kw: score_candidates(
            model, depth, actions, mirror=mirror, views=views, **kw))
        self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F()))
        self.DeclareAbstractInputPort("candidate_actions", AbstractValue.Make(np.zeros((0, 3))))
        if self._needs_height:
            self.DeclareVectorInputPort("camera_height", 1)
        self.DeclareAbstractOutputPort(
            "predicted_distances", lambda: AbstractValue.Make(np.zeros(0)),
            self._CalcDistances)

    def _CalcDistances(self, context, output):
        depth = self.get_input_port(0).Eval(context).data[:, :, 0]
        actions = self.get_input_port(1).Eval(context)
        if not len(actions):
            output.set_value(np.zeros(0))
        elif self._needs_height:
            h = float(self.GetInputPort("camera_height").Eval(context)[0])
            output.set_value(self._score_fn(depth, actions, camera_height_m=h))
        else:
            output.set_value(self._score_fn(depth, actions))


class ActionSampler(LeafSystem):
    """Candidate actions near the current pose, fresh for every control step.

    The draw of step k depends only on (trial seed, k): `default_rng([seed, k, 17])`.

    Output ports:
        candidate_actions: (K, 3) actions uniform in [-xy, xy]^2 x [-theta, theta].
    Parameters:
        seed (numeric, 1 element): the trial seed; `set_seed`.
    """

    def __init__(self, *, num_candidates: int, xy_m: float, theta_deg: float, period_s: float,
                 seed: int = 0):
        super().__init__()
        self._k = int(num_candidates)
        self._xy = float(xy_m)
        self._theta = float(theta_deg)
        self._period = float(period_s)
        self._seed = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.DeclareAbstractOutputPort(
            "candidate_actions", lambda: AbstractValue.Make(np.zeros((0, 3))), self._Calc,
            {self.time_ticket(), self.numeric_parameter_ticket(NumericParameterIndex(self._seed))})

    def set_seed(self, context, seed: int) -> None:
        context.get_mutable_numeric_parameter(self._seed).SetAtIndex(0, float(seed))

    def step_index(self, context) -> int:
        return int(round(context.get_time() / self._period))

    def _Calc(self, context, output):
        seed = int(context.get_numeric_parameter(self._seed).GetAtIndex(0))
        rng = np.random.default_rng([seed, self.step_index(context), 17])
        output.set_value(sample_candidates(rng, self._k, xy_m=self._xy, theta_deg=self._theta))
