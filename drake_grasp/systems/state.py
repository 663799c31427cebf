"""Abstract-state values that a Context may share instead of deep-copying."""

from __future__ import annotations

import dataclasses


def shared_when_copied(cls: type) -> type:
    """Class decorator: copies of an instance are the instance itself.

    For the frozen dataclasses the LeafSystems here keep in a Context's abstract state.
    Before every unrestricted update a Diagram copies its whole state as the baseline of
    the update, and pydrake copies a Python value with `copy.deepcopy`: with the judge
    sampling at 100 Hz, the controller's state (its last depth image and candidates) and
    the frame buffer's images were deep-copied about a thousand times per episode, ~5%
    of an episode's wall time. The systems never change a state value in place (an
    update builds a new value with `dataclasses.replace` and sets it), so a copy can be
    the value itself, as for a tuple of numbers. Arrays kept in such a value should be
    made read-only (`freeze`) so that an accidental in-place change fails loudly.

    Raises:
        TypeError: `cls` is not a frozen dataclass.
    """
    params = getattr(cls, "__dataclass_params__", None)
    if not dataclasses.is_dataclass(cls) or params is None or not params.frozen:
        raise TypeError(f"shared_when_copied: {cls.__name__} must be a frozen dataclass")
    cls.__copy__ = lambda self: self
    cls.__deepcopy__ = lambda self, memo: self
    return cls


def freeze(array):
    """`array` made read-only (in place) and returned, for arrays kept in a state value."""
    array.setflags(write=False)
    return array


__all__ = ["freeze", "shared_when_copied"]
