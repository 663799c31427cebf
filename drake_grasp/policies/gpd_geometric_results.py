"""What the geometric detector returns: its detections and the weights of their score.

`ScoreWeights` holds the weight of each score term (`SCORE_TERMS`, each term in
[0, 1]; see `gpd_geometric`'s module docstring for what they measure), `DetectedGrasps`
the detections of one image sorted best first (centres, yaws, heights, widths, scores,
contact patches and their normals, the terms) with their top-down poses, and `Grasp`
the single best one. Top-down convention of `drake_grasp.geometry.grasps`:
R_WG = Rz(theta) Rx(pi), theta the yaw of the closing direction x_G in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drake_grasp.geometry.hand_model import topdown_rotation
from drake_grasp.policies.gpd_geometric_checks import _finite


@dataclass(frozen=True)
class ScoreWeights:
    """Weights of the score terms (each term in [0, 1]; see the module docstring)."""

    antipodal: float = 1.0
    centring: float = 1.0
    balance: float = 1.0
    clearance: float = 0.5
    fill: float = 0.5
    depth: float = 1.0
    view: float = 0.05

    def validate(self) -> None:
        for name in SCORE_TERMS:
            _finite(f"weights.{name}", getattr(self, name), low=0.0)


SCORE_TERMS = ("antipodal", "centring", "balance", "clearance", "fill", "depth", "view")


@dataclass(frozen=True)
class Grasp:
    """One detected top-down grasp.

    Attributes:
        xy_theta: (3,) grasp centre x, y [m] and closing-direction yaw theta [deg] in
            [0, 180).
        z: Height of the grasp centre [m].
        width: What the pads close to [m].
        score: Its score (higher is better).
    """

    xy_theta: np.ndarray
    z: float
    width: float
    score: float

    @property
    def hand_pose(self) -> np.ndarray:
        """[x, y, z, yaw_deg] of the grasp frame (the format `SceneRenderer` takes)."""
        return np.array([self.xy_theta[0], self.xy_theta[1], self.z, self.xy_theta[2]])

    @property
    def pose(self) -> np.ndarray:
        """(4, 4) X_WG of the grasp frame."""
        X = np.eye(4)
        X[:3, :3] = topdown_rotation(np.deg2rad(self.xy_theta[2]))
        X[:3, 3] = [self.xy_theta[0], self.xy_theta[1], self.z]
        return X


@dataclass(frozen=True)
class DetectedGrasps:
    """Detections of one image, best first.

    Attributes:
        xy_theta: (N, 3) grasp centres x, y [m] and yaw theta [deg] in [0, 180) of
            the closing direction x_G, in the world.
        z: (N,) heights of the grasp centres [m].
        width: (N,) what the pads close to (extent of the closing region) [m].
        score: (N,) scores, descending.
        contacts: (N, 2, 3) centroids of the two contact patches as seen (-x_G side
            first) [m].
        contact_normals: (N, 2, 3) their mean outward unit normals.
        terms: Score terms by name (`SCORE_TERMS`), each (N,) in [0, 1].
    """

    xy_theta: np.ndarray
    z: np.ndarray
    width: np.ndarray
    score: np.ndarray
    contacts: np.ndarray
    contact_normals: np.ndarray
    terms: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.score)

    @classmethod
    def empty(cls) -> DetectedGrasps:
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0),
                   np.zeros((0, 2, 3)), np.zeros((0, 2, 3)), {k: np.zeros(0) for k in SCORE_TERMS})

    def poses(self) -> np.ndarray:
        """(N, 4, 4) X_WG of the grasp frames (top-down: R_WG = Rz(theta) Rx(pi))."""
        th = np.deg2rad(self.xy_theta[:, 2])
        c, s = np.cos(th), np.sin(th)
        X = np.zeros((len(self), 4, 4))
        X[:, 0, 0], X[:, 1, 0] = c, s
        X[:, 0, 1], X[:, 1, 1] = s, -c
        X[:, 2, 2] = -1.0
        X[:, :2, 3] = self.xy_theta[:, :2]
        X[:, 2, 3] = self.z
        X[:, 3, 3] = 1.0
        return X

    def hand_poses(self) -> np.ndarray:
        """(N, 4) [x, y, z, yaw_deg] of the grasp frames."""
        return np.column_stack([self.xy_theta[:, :2], self.z, self.xy_theta[:, 2]])

    def best(self) -> Grasp | None:
        """The top detection, or None when there is none."""
        if len(self) == 0:
            return None
        return Grasp(self.xy_theta[0].copy(), float(self.z[0]), float(self.width[0]),
                     float(self.score[0]))
