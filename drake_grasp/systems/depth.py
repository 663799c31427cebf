"""Drake wrapper around the depth post-processing pipeline of `drake_grasp.geometry.sensing`."""

from __future__ import annotations

import copy
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, LeafSystem, NumericParameterIndex
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.geometry.sensing import DepthNoiseConfig, frame_rng, postprocess_depth

# The seed is stored as a double parameter; integers are exact up to 2**53.
_MAX_SEED = 2**53


class DepthPostProcessor(LeafSystem):
    """Adds sensor noise to the rendered depth image and fills its holes.

    Runs `drake_grasp.geometry.sensing.postprocess_depth` on each evaluation. The output is
    a pure function of (input image, seed parameter, time), so it is safe with
    Drake's output caching: the noise of camera frame
    ``round(t / frame_period_s)`` comes from ``frame_rng(seed, frame)``.

    The trial seed is a numeric parameter in the Context, so a Monte Carlo loop
    changes it per trial with `set_seed` without rebuilding the Diagram. `stream`
    tells the cameras of one trial apart: each draws its own noise from the seed.

    .. pydrake_system::

        name: DepthPostProcessor
        input_ports:
        - depth_image_32f
        output_ports:
        - depth_image

    Ports:
        depth_image_32f (input, abstract ImageDepth32F): clean depth [m] from an
            RgbdSensor's ``depth_image_32f`` output (0 below near clip, +inf
            beyond far clip).
        depth_image (output, abstract ImageDepth32F): noisy (if enabled), hole-
            filled depth [m]; every pixel finite, far pixels ``far_value_m``, and so
            are pixels left unfilled (all invalid ones when
            ``fill_max_iterations`` is 0).
    """

    def __init__(
        self,
        config: DepthNoiseConfig,
        *,
        width: int,
        height: int,
        far_value_m: float,
        frame_period_s: float,
        seed: int = 0,
        stream: int = 0,
    ) -> None:
        """Builds the system.

        Args:
            config: Noise and filter parameters (copied; validated here).
            width: Image width [pixels], > 0.
            height: Image height [pixels], > 0.
            far_value_m: Depth for far and unfillable pixels [m], finite > 0.
            frame_period_s: Camera frame period [s], finite > 0.
            seed: Default trial seed, 0 <= seed < 2**53.
            stream: This camera's noise stream (`sensing.frame_rng`), an int >= 0.

        Raises:
            ValueError: For an invalid config or argument.
        """
        super().__init__()
        config.validate()
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{name} must be an int > 0 (got {value!r})")
        for name, value in (("far_value_m", far_value_m), ("frame_period_s", frame_period_s)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite number > 0 (got {value!r})")
        _check_seed(seed)
        if isinstance(stream, bool) or not isinstance(stream, (int, np.integer)) or stream < 0:
            raise ValueError(f"stream must be an int >= 0 (got {stream!r})")
        self._stream = int(stream)
        # A private copy: the caller mutating its config later must not silently
        # change an already-built system.
        self._config = copy.deepcopy(config)
        self._width = int(width)
        self._height = int(height)
        self._far_value_m = float(far_value_m)
        self._frame_period_s = float(frame_period_s)

        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self._input = self.DeclareAbstractInputPort(
            "depth_image_32f", AbstractValue.Make(ImageDepth32F(self._width, self._height))
        )
        self.DeclareAbstractOutputPort(
            "depth_image",
            lambda: AbstractValue.Make(ImageDepth32F(self._width, self._height)),
            self._CalcDepthImage,
            prerequisites_of_calc={
                self.time_ticket(),
                self.input_port_ticket(self._input.get_index()),
                self.numeric_parameter_ticket(NumericParameterIndex(self._seed_index)),
            },
        )

    @property
    def config(self) -> DepthNoiseConfig:
        """A copy of the noise configuration this system was built with."""
        return copy.deepcopy(self._config)

    def set_seed(self, context: Context, seed: int) -> None:
        """Sets the trial seed in `context` (0 is valid).

        Raises:
            ValueError: Unless 0 <= seed < 2**53 is an int.
        """
        _check_seed(seed)
        self.ValidateContext(context)
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    def get_seed(self, context: Context) -> int:
        """The trial seed stored in `context`."""
        self.ValidateContext(context)
        return int(context.get_numeric_parameter(self._seed_index).GetAtIndex(0))

    def frame_index(self, context: Context) -> int:
        """The camera frame number whose noise `context`'s time selects."""
        return int(round(context.get_time() / self._frame_period_s))

    def _CalcDepthImage(self, context: Context, output: AbstractValue) -> None:
        image = self._input.Eval(context)
        if image.width() != self._width or image.height() != self._height:
            raise ValueError(
                f"DepthPostProcessor expects a {self._width}x{self._height} depth image "
                f"(got {image.width()}x{image.height()})"
            )
        rng = None
        if self._config.enabled:
            rng = frame_rng(self.get_seed(context), self.frame_index(context), self._stream)
        processed = postprocess_depth(image.data, rng, self._config, self._far_value_m)
        output.get_mutable_value().mutable_data[:] = processed


def _check_seed(seed: int) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int in [0, 2**53) (got {seed!r})")
    if not 0 <= seed < _MAX_SEED:
        raise ValueError(f"seed must be an int in [0, 2**53) (got {seed!r})")
