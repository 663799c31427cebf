"""Frames as a real control loop receives them: late (latency) and sometimes not at all
(dropped frames). See `scenario.TimingConfig`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from drake_grasp.systems.state import freeze, shared_when_copied

# Random stream of the dropped-frame draws (`np.random.default_rng([seed, frame, 89])`).
DROP_STREAM = 89
# Tolerance on event times [s] (Drake computes them in double).
_EPS = 1e-9


def frame_dropped(seed: int, frame: int, prob: float) -> bool:
    """Whether frame `frame` (>= 1; frame 0, the one at the start, always arrives) of
    trial `seed` is lost. The same draw for every image stream of that frame."""
    if prob <= 0.0 or frame <= 0:
        return False
    return bool(np.random.default_rng([int(seed), int(frame), DROP_STREAM]).random() < prob)


@shared_when_copied
@dataclass(frozen=True)
class _Frames:
    """The FrameBuffer's memory: what the policy gets for each recent capture.

    `frames` holds (capture index, image array) pairs, oldest first; index -1 is the
    image at the start (t = 0), which stands for every capture before the first.
    """

    frames: tuple = ()


class FrameBuffer(LeafSystem):
    """Delays an image stream by a latency and drops frames, as a sensor link would.

    A frame is captured at the times `k * period_s - latency_s` (k = 1, 2, ...), so that
    a policy deciding at its control ticks `k * period_s` gets the frame taken
    `latency_s` earlier; between ticks the output is the newest frame at least
    `latency_s` old. A dropped frame (`frame_dropped`) is replaced by the last frame that
    arrived. The image at t = 0 stands for every capture before the start (the robot
    rests there). With no latency the output at a tick is the live image of that tick.

    Input ports:
        image: the live image (any Drake image type; `model` gives it).
    Output ports:
        image: the image the policy receives.
    State:
        abstract `_Frames`: the recent captures (as many as the latency spans, + 2).
    """

    def __init__(self, model, *, period_s: float, latency_s: float, dropped_frame_prob: float,
                 seed: int):
        """Args:
            model: an image of the stream's type (e.g. `ImageDepth32F()`).
            period_s: the control period (one frame per period) [s], > 0.
            latency_s: sensor-to-action latency [s], >= 0.
            dropped_frame_prob: probability that a frame is lost, in [0, 1).
            seed: the trial's seed (the dropped-frame draws).
        """
        super().__init__()
        if not period_s > 0.0:
            raise ValueError(f"FrameBuffer: period_s must be > 0, got {period_s!r}")
        if not latency_s >= 0.0:
            raise ValueError(f"FrameBuffer: latency_s must be >= 0, got {latency_s!r}")
        if not 0.0 <= dropped_frame_prob < 1.0:
            raise ValueError(f"FrameBuffer: dropped_frame_prob must be in [0, 1), got "
                             f"{dropped_frame_prob!r}")
        self._period = float(period_s)
        self._latency = float(latency_s)
        self._prob = float(dropped_frame_prob)
        self._seed = int(seed)
        self._type = type(model)
        # Capture times o + j * period with o in [0, period): j counts captures.
        self._offset = (-self._latency) % self._period
        if self._offset > self._period - _EPS:
            self._offset = 0.0
        self._keep = int(math.ceil(self._latency / self._period)) + 2
        self._input = self.DeclareAbstractInputPort("image", AbstractValue.Make(model))
        self._state = self.DeclareAbstractState(AbstractValue.Make(_Frames()))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._Initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, self._offset, self._Capture)
        self.DeclareAbstractOutputPort("image", lambda: AbstractValue.Make(model), self._Calc)

    # -- timing ---------------------------------------------------------------------

    def capture_time(self, index: int) -> float:
        return self._offset + index * self._period

    def _index_at(self, t: float) -> int:
        """The newest capture index whose time is <= t (-1: none yet)."""
        return int(math.floor((t - self._offset) / self._period + _EPS))

    def _arrived(self, index: int) -> bool:
        # The capture at t = 0 (offset 0) is the start image: it always arrives.
        frame = index + (1 if self._offset > 0.0 else 0)
        return not frame_dropped(self._seed, frame, self._prob)

    # -- events -----------------------------------------------------------------------

    def _live(self, context) -> np.ndarray:
        return freeze(np.array(self._input.Eval(context).data, copy=True))

    def _Initialize(self, context, state):
        state.get_mutable_abstract_state(int(self._state)).set_value(
            _Frames(((-1, self._live(context)),)))

    def _Capture(self, context, state):
        frames = context.get_abstract_state(int(self._state)).get_value().frames
        index = int(round((context.get_time() - self._offset) / self._period))
        image = self._live(context) if self._arrived(index) else frames[-1][1]
        kept = (frames + ((index, image),))[-self._keep:]
        state.get_mutable_abstract_state(int(self._state)).set_value(_Frames(kept))

    # -- output -----------------------------------------------------------------------

    def _Calc(self, context, output):
        frames = context.get_abstract_state(int(self._state)).get_value().frames
        t = context.get_time()
        want = self._index_at(t - self._latency)
        if not frames:  # before Initialize: the live image
            array = self._live(context)
        elif want > frames[-1][0] and abs(self.capture_time(want) - t) < 1e-6:
            # The capture due now (no latency) is applied after this instant's updates:
            # the live image is that frame.
            array = self._live(context) if self._arrived(want) else frames[-1][1]
        else:
            array = frames[0][1]
            for index, image in frames:
                if index <= want:
                    array = image
        out = output.get_mutable_value()
        height, width = array.shape[:2]
        if out.width() != width or out.height() != height:
            out.resize(width, height)
        out.mutable_data[:] = array
