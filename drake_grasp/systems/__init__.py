"""Drake LeafSystems of the drake_grasp Diagram."""

from drake_grasp.systems.depth import DepthPostProcessor

__all__ = ["DepthPostProcessor"]
