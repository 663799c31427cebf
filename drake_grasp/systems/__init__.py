"""Drake LeafSystems shared by every episode, whatever the policy: depth post-processing
(`depth`), the gripper's driver (`gripper`), the shared grasp motion (`supervisor`,
`monitor`), the frame buffer (`frames`), disturbances (`disturbance`), the arm's
execution error between a policy's command and the station (`kinematic_noise`) and the
judge (`judge`), the only system with privileged ports.

Floor 6: imports `config` and the floors below."""

from drake_grasp.systems.depth import DepthPostProcessor

__all__ = ["DepthPostProcessor"]
