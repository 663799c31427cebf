"""drake_grasp: a Drake systems-diagram model of closed-loop visuomotor grasping.

Re-creates "Learning a visuomotor controller for real world robotic grasping using
simulated depth images" (Viereck et al., CoRL 2017) with contact physics.
"""

__version__ = "0.1.0"
