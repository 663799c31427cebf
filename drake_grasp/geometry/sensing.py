"""Depth-image noise model and hole filling for the simulated wrist camera.

Pure numpy (no Drake import) so the same code runs inside the Diagram
(`drake_grasp.systems.depth.DepthPostProcessor`) and in the offline dataset
generator: both call `postprocess_depth`, so training and closed-loop images are
produced by one pipeline.

Pixel conventions (Drake's `RgbdSensor` depth output is noiseless, in metres):

* A finite value > 0 is a depth measurement.
* ``+inf`` (Drake: beyond the far clip) is a real reading meaning "nothing there,
  far"; `fill_invalid_depth` replaces it with ``far_value_m`` directly instead of
  filling it from neighbours.
* `INVALID_DEPTH` (0.0; Drake: below the near clip, or a dropped-out pixel), any
  value <= 0, NaN and ``-inf`` are missing data, which `fill_invalid_depth` fills
  with the neighbourhood maximum as in Viereck et al. (CoRL 2017).
"""


import math
from dataclasses import dataclass

import numpy as np

INVALID_DEPTH: float = 0.0
"""Value marking a pixel with no depth reading (Drake uses 0 below the near clip)."""


@dataclass
class DepthNoiseConfig:
    """Parameters of the structured-light depth noise model.

    The model has three parts, applied to the clean rendered depth ``z`` (metres):

    1. Axial Gaussian noise with a depth-dependent standard deviation, after
       Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise for Improved 3D
       Reconstruction and Tracking", 3DIMPVT 2012, whose fit for the Kinect v1 is
       ``sigma_z = 0.0012 + 0.0019 * (z - 0.4)**2`` metres (surface angles up to
       60 degrees; their extra grazing-angle term is omitted because it needs
       surface normals). Here::

           sigma(z) = sigma_base_m
                      + sigma_quadratic_per_m2 * max(z - sigma_reference_depth_m, 0)**2

       The quadratic is centred on 0.4 m for the Kinect's working range; closer
       than that the unclamped fit would make noise *grow* toward the camera,
       which the model was not fitted to describe, so sigma is held at
       ``sigma_base_m`` there (a wrist camera works at 0.2-0.6 m).
    2. Edge dropout: real structured-light and ToF sensors lose pixels at object
       silhouettes (pattern occlusion, mixed pixels). Each valid pixel whose
       depth differs from a 4-neighbour by more than ``edge_threshold_m`` is
       dropped with probability ``edge_dropout_prob``.
    3. Random dropout of isolated pixels with probability ``random_dropout_prob``.

    The edge and dropout defaults are engineering choices (no single published
    value exists); they give thin ragged silhouette holes and a sparse speckle of
    missing pixels, which the hole filter then closes.

    Attributes:
        enabled: Whether `postprocess_depth` adds noise at all. Off by default so
            the baseline simulation matches the paper's noiseless rendering.
        sigma_base_m: Noise standard deviation at and below the reference depth
            [m]; Nguyen et al.: 0.0012.
        sigma_quadratic_per_m2: Growth of sigma per squared metre beyond the
            reference depth [m / m^2]; Nguyen et al.: 0.0019.
        sigma_reference_depth_m: Depth at which the quadratic term starts [m];
            Nguyen et al.: 0.4.
        edge_threshold_m: Depth jump between 4-neighbours that counts as a
            discontinuity [m]; must be > 0.
        edge_dropout_prob: Probability that a pixel next to a discontinuity is
            dropped, in [0, 1].
        random_dropout_prob: Probability that any valid pixel is dropped, in [0, 1].
        fill_max_iterations: Iterations of the hole-filling dilation; each grows
            the filled region by one pixel, so 64 crosses a whole 64x64 image and
            only an all-invalid image falls back to the far value. >= 0.
    """

    enabled: bool = False
    sigma_base_m: float = 0.0012
    sigma_quadratic_per_m2: float = 0.0019
    sigma_reference_depth_m: float = 0.4
    edge_threshold_m: float = 0.02
    edge_dropout_prob: float = 0.5
    random_dropout_prob: float = 0.005
    fill_max_iterations: int = 64

    def validate(self) -> None:
        """Checks every field.

        Raises:
            ValueError: Naming the first bad field and its expected range.
        """
        if not isinstance(self.enabled, (bool, np.bool_)):
            raise ValueError(
                f"DepthNoiseConfig.enabled must be a bool (got {self.enabled!r})"
            )
        for name in ("sigma_base_m", "sigma_quadratic_per_m2", "sigma_reference_depth_m"):
            _check_real(name, getattr(self, name), low=0.0, low_inclusive=True)
        _check_real("edge_threshold_m", self.edge_threshold_m, low=0.0, low_inclusive=False)
        for name in ("edge_dropout_prob", "random_dropout_prob"):
            _check_real(name, getattr(self, name), low=0.0, low_inclusive=True, high=1.0)
        value = self.fill_max_iterations
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise ValueError(
                f"DepthNoiseConfig.fill_max_iterations must be an int >= 0 (got {value!r})"
            )
        if value < 0:
            raise ValueError(
                f"DepthNoiseConfig.fill_max_iterations must be an int >= 0 (got {value!r})"
            )

    def sigma_at(self, depth_m: np.ndarray | float) -> np.ndarray | float:
        """Axial noise standard deviation [m] at the given depth(s) [m]."""
        excess = np.maximum(np.asarray(depth_m) - self.sigma_reference_depth_m, 0.0)
        return self.sigma_base_m + self.sigma_quadratic_per_m2 * excess**2


def _check_real(
    name: str,
    value: object,
    *,
    low: float,
    low_inclusive: bool,
    high: float | None = None,
) -> None:
    """Raises ValueError unless `value` is a finite real in the given range."""
    if high is not None:
        expected = f"in [{low:g}, {high:g}]"
    else:
        expected = f">= {low:g}" if low_inclusive else f"> {low:g}"
    message = f"DepthNoiseConfig.{name} must be a finite number {expected} (got {value!r})"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(message)
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(message)
    if value < low or (value == low and not low_inclusive):
        raise ValueError(message)
    if high is not None and value > high:
        raise ValueError(message)


def frame_rng(seed: int, frame_index: int, stream: int = 0) -> np.random.Generator:
    """The noise generator for one camera frame of one trial.

    A frame's noise depends only on (seed, frame_index, stream), never on how many
    frames were rendered before or in which order, so Drake may re-evaluate (or skip)
    frames freely and a dataset frame can be regenerated on its own.

    Args:
        seed: Trial seed, >= 0 (0 is a valid seed).
        frame_index: Camera frame number, >= 0.
        stream: Which camera of the trial, >= 0: each stream draws its own noise from
            the same trial seed (0, the wrist camera, keeps the draws it always had).

    Raises:
        ValueError: If any is negative or not an integer.
    """
    for name, value in (("seed", seed), ("frame_index", frame_index), ("stream", stream)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name} must be an int >= 0 (got {value!r})")
        if value < 0:
            raise ValueError(f"{name} must be an int >= 0 (got {value!r})")
    if stream == 0:
        return np.random.default_rng([int(seed), int(frame_index)])
    return np.random.default_rng([int(seed), int(frame_index), int(stream)])


def _as_2d(depth: np.ndarray) -> np.ndarray:
    """A (h, w) view of a (h, w) or (h, w, 1) depth array (Drake's `image.data`)."""
    depth = np.asarray(depth)
    if depth.ndim == 3 and depth.shape[2] == 1:
        return depth[:, :, 0]
    if depth.ndim == 2:
        return depth
    raise ValueError(f"depth must have shape (h, w) or (h, w, 1) (got {depth.shape})")


def _edge_mask(depth: np.ndarray, threshold_m: float) -> np.ndarray:
    """Pixels on either side of a 4-neighbour depth jump larger than the threshold.

    `depth` holds NaN for missing pixels (a hole is not a discontinuity, and NaN
    comparisons are False) and +inf for far pixels (a finite pixel next to +inf is
    a silhouette against empty background).
    """
    edges = np.zeros(depth.shape, dtype=bool)
    with np.errstate(invalid="ignore"):  # inf - inf -> NaN, which compares False
        jump = np.abs(depth[:, 1:] - depth[:, :-1]) > threshold_m
        edges[:, 1:] |= jump
        edges[:, :-1] |= jump
        jump = np.abs(depth[1:, :] - depth[:-1, :]) > threshold_m
        edges[1:, :] |= jump
        edges[:-1, :] |= jump
    return edges


def apply_depth_noise(
    depth: np.ndarray, rng: np.random.Generator, config: DepthNoiseConfig
) -> np.ndarray:
    """Adds the `DepthNoiseConfig` sensor model to a clean depth image.

    Finite positive pixels get Gaussian noise and may be dropped; ``+inf`` (far)
    pixels pass through unchanged; every other pixel (<= 0, NaN, -inf) becomes
    `INVALID_DEPTH`. A noisy value that would be <= 0 is also marked invalid.
    Discontinuities are found on the clean input. The generator always draws the
    same arrays in the same order, so e.g. changing a dropout probability does
    not change the Gaussian noise sample.

    Args:
        depth: Depth [m], shape (h, w) or (h, w, 1).
        rng: Noise source; see `frame_rng`.
        config: Noise parameters.

    Returns:
        A new float32 array of the input's shape. If ``config.enabled`` is False,
        a plain float32 copy (not even invalid values are normalised).
    """
    src = np.asarray(depth)
    if not config.enabled:
        return np.array(src, dtype=np.float32, copy=True)
    config.validate()
    z = _as_2d(src).astype(np.float32)  # always a copy
    far = np.isposinf(z)
    valid = np.isfinite(z) & (z > 0.0)

    # Fixed draw order and sizes: normal, then two uniforms.
    normal = rng.standard_normal(z.shape, dtype=np.float32)
    uniform = rng.random((2,) + z.shape, dtype=np.float32)

    edges = _edge_mask(np.where(valid | far, z, np.float32(np.nan)), config.edge_threshold_m)

    sigma = np.float32(config.sigma_base_m) + np.float32(config.sigma_quadratic_per_m2) * (
        np.square(np.maximum(z - np.float32(config.sigma_reference_depth_m), np.float32(0.0)))
    )
    with np.errstate(invalid="ignore"):  # inf/NaN pixels; overwritten below
        out = z + sigma * normal
    dropped = (edges & (uniform[0] < config.edge_dropout_prob)) | (
        uniform[1] < config.random_dropout_prob
    )
    keep = valid & ~dropped & (out > 0.0)
    out = np.where(keep, out, np.float32(INVALID_DEPTH))
    out[far] = np.inf
    return out.reshape(src.shape)


def fill_invalid_depth(
    depth: np.ndarray, max_iterations: int, far_value_m: float
) -> np.ndarray:
    """The paper's hole filter: iterative dilation with the neighbourhood maximum.

    ``+inf`` (beyond the far clip) is a real "far" reading, so it is set to
    ``far_value_m`` first and then counts as a valid neighbour. Pixels that are
    <= 0, NaN or -inf are invalid. Each iteration, every invalid pixel with at
    least one valid pixel in its 3x3 neighbourhood takes the maximum of those
    valid neighbours (all updates use the previous iteration's image). Iteration
    stops when nothing is invalid, nothing changed, or after `max_iterations`;
    pixels still invalid then (e.g. an all-invalid image) become ``far_value_m``.
    Taking the maximum fills silhouette holes with the background depth, as
    Viereck et al. (CoRL 2017) do.

    Args:
        depth: Depth [m], shape (h, w) or (h, w, 1).
        max_iterations: Dilation iterations, >= 0.
        far_value_m: Depth used for far and unfillable pixels [m], finite > 0.

    Returns:
        A new float32 array of the input's shape, all finite and > 0.

    Raises:
        ValueError: For a bad shape, negative `max_iterations` or bad `far_value_m`.
    """
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0 (got {max_iterations!r})")
    if not (math.isfinite(far_value_m) and far_value_m > 0.0):
        raise ValueError(f"far_value_m must be a finite number > 0 (got {far_value_m!r})")
    src = np.asarray(depth)
    z = _as_2d(src)
    h, w = z.shape
    # Work in the interior of a -inf padded buffer: invalid pixels are -inf, so a
    # plain 3x3 max (done separably) is the max over valid neighbours, and a
    # result of -inf means "no valid neighbour".
    padded = np.full((h + 2, w + 2), -np.inf, dtype=np.float32)
    work = padded[1:-1, 1:-1]
    work[...] = z
    work[np.isposinf(work)] = far_value_m
    invalid = ~(work > 0.0)  # catches <= 0 and NaN
    work[invalid] = -np.inf
    for _ in range(max_iterations):
        if not invalid.any():
            break
        rows = np.maximum(np.maximum(padded[:, :-2], padded[:, 1:-1]), padded[:, 2:])
        neighbourhood_max = np.maximum(np.maximum(rows[:-2], rows[1:-1]), rows[2:])
        fill = invalid & (neighbourhood_max > -np.inf)
        if not fill.any():
            break
        work[fill] = neighbourhood_max[fill]
        invalid &= ~fill
    work[invalid] = far_value_m
    return work.copy().reshape(src.shape)


def postprocess_depth(
    raw: np.ndarray,
    rng: np.random.Generator | None,
    config: DepthNoiseConfig,
    far_value_m: float,
) -> np.ndarray:
    """The one depth pipeline used by the Diagram and the dataset generator.

    Noise (if ``config.enabled``) then `fill_invalid_depth` with
    ``config.fill_max_iterations``.

    Args:
        raw: Clean rendered depth [m], shape (h, w) or (h, w, 1), Drake
            conventions (0 below near clip, +inf beyond far clip).
        rng: Noise source (see `frame_rng`); may be None when noise is disabled.
        config: Noise and filter parameters.
        far_value_m: Depth for far and unfillable pixels [m].

    Returns:
        A new float32 array of the input's shape, all finite.

    Raises:
        ValueError: For an invalid config, an enabled config with no `rng`, or
            bad arguments.
    """
    config.validate()
    if config.enabled:
        if rng is None:
            raise ValueError("postprocess_depth needs an rng when config.enabled is True")
        raw = apply_depth_noise(raw, rng, config)
    return fill_invalid_depth(raw, config.fill_max_iterations, far_value_m)
