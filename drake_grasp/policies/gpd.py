"""Grasp pose detection (GPD), the paper's baseline, with a learned grasp classifier.

Viereck et al. (CoRL 2017) compare their controller with grasp pose detection
(Gualtieri, ten Pas, Saenko & Platt, "High precision grasp pose detection in dense
clutter", IROS 2016; ten Pas, Gualtieri, Saenko & Platt, "Grasp Pose Detection in Point
Clouds", IJRR 2017), run once: the hand moves to a fixed pose above the table, an
accurate depth sensor (a Structure IO) takes one image, and the selected detection is
executed open loop. This module is that pipeline, written from the published
description; it is pure numpy / scipy / torch (no Drake):

1. **Point cloud** (`cloud_from_depth`): the image back-projected to the world (the
   camera pose the robot believes it has), cropped to the workspace, the table and the
   sheet removed (points below ``table_z + table_margin_m``), voxelised
   (`voxel_m`, 2 mm), surface normals from a PCA of each point's `k` nearest
   neighbours (turned toward the camera), and the axis of least curvature from a PCA of
   the neighbours' normals (GPD's local reference frame).
2. **Candidates** (`sample_hands`): `num_samples` cloud points drawn uniformly; at each,
   approach directions within a cone of `approach_max_tilt_deg` about straight down
   (straight down, and the inward surface normal pulled into the cone), `num_rotations`
   closing directions about each approach (the first across the curvature axis, the
   others evenly over 180 degrees) and several depths below the local top, as GPD
   searches orientations and pushes the hand in.
3. **Geometric filters** (`grasps.evaluate_hands`): the open hand, swept in along its
   approach, touches no cloud point and stays above the table; at least
   `min_points_between` cloud points lie in the closing region, spanning a width the
   85 mm stroke can close on.
4. **Grasp images** (`grasp_images`): the cloud points in the closing region's cube
   (side 85 mm, the stroke, centred between the pads), in the hand frame, projected
   onto the hand's three planes; per projection an occupancy, a normal (3 channels) and
   a depth channel: 15 channels of `IMAGE_SIZE` x `IMAGE_SIZE` (GPD's 15-channel
   representation; 32 px instead of GPD's 60 over the 85 mm cube is 2.7 mm per pixel,
   near the 2 mm cloud).
5. **Classifier** (`GraspClassifier`): GPD's LeNet (conv 20@5x5, pool, conv 50@5x5,
   pool, 500 inner product, ReLU, output) giving the probability that a candidate is a
   grasp; trained on candidates from simulated scenes labelled by this project's
   physics-consistent ground truth (`drake_grasp.learning.gpd_training`).
6. **Selection** (`select`): after Gualtieri et al. 2016, who cluster aligned detections
   for precision in dense clutter: detections are the candidates the classifier accepts
   (probability >= `threshold`), ranked by the mean probability of the candidates
   aligned with each (centres within 1 cm, approach and closing axes within 15
   degrees).

Conventions (`drake_grasp.geometry.grasps`): the grasp frame G sits between the pads, z_G is the
approach, x_G the closing direction.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.geometry.grasp_candidates import DEFAULT_DEPTHS_M
from drake_grasp.geometry.hand_checks import evaluate_hands, evaluation_poses
from drake_grasp.geometry.hand_model import STROKE_M, TABLE_TOP_Z_M
from drake_grasp.geometry.scene_samples import ScenePoints
from drake_grasp.policies.gpd_ranking import Detections, Selection, select

# The weights files' format id (in their metadata; the shipped models/gpd/ carries it): a name,
# not a module path.
WEIGHTS_FORMAT = "drake_grasp.gpd.GraspClassifier"
IMAGE_SIZE = 32
CHANNELS = 15
# Half side of the cube imaged around the grasp centre [m]: the stroke.
REGION_HALF_M = 0.5 * STROKE_M


# ----------------------------------------------------------------------------
# Point cloud.


@dataclass(frozen=True)
class Cloud:
    """An object point cloud with GPD's local frames.

    Attributes:
        points: (N, 3) world positions [m].
        normals: (N, 3) unit surface normals facing the camera.
        axes: (N, 3) unit axes of least curvature (PCA of the neighbours' normals).
        camera: (3,) the camera position the cloud was seen from.
    """

    points: np.ndarray
    normals: np.ndarray
    axes: np.ndarray
    camera: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def back_project(depth, *, fov_y_deg: float, X_WC, depth_min_m: float,
                 depth_max_m: float) -> np.ndarray:
    """World points (N, 3) of the pixels with a reading inside [depth_min_m, depth_max_m).

    Drake's depth is along the optical axis; pixel (row v, column u) at depth d is the
    camera-frame point d ((u - cu) / f, (v - cv) / f, 1). Pixels with no reading (0,
    NaN, +inf, or the far value a post-processor writes) are dropped.

    Raises:
        ValueError: not a 2-D image (or (H, W, 1)), or a pose that is not 4x4.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"depth: expected an (H, W) image, got shape {np.shape(depth)}")
    X = np.asarray(getattr(X_WC, "GetAsMatrix4", lambda: X_WC)(), dtype=float)
    if X.shape != (4, 4) or not np.all(np.isfinite(X)):
        raise ValueError(f"X_WC: expected a finite 4x4 pose, got shape {X.shape}")
    H, W = d.shape
    camera = PinholeCamera.from_fov(W, H, fov_y_deg)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d >= depth_min_m) & (d < depth_max_m * (1.0 - 1e-6))
    v, u = np.nonzero(valid)
    z = d[v, u]
    x, y = camera.back_project(u, v, z)
    P_C = np.stack([x, y, z], axis=1)
    return P_C @ X[:3, :3].T + X[:3, 3]


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per occupied voxel of side `voxel_m`: the mean of its points."""
    if len(points) == 0:
        return np.zeros((0, 3))
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    out = np.zeros((len(counts), 3))
    for j in range(3):
        out[:, j] = np.bincount(inverse, points[:, j], minlength=len(counts))
    return out / counts[:, None]


def _smallest_eigenvectors(cov: np.ndarray) -> np.ndarray:
    """Eigenvector of the smallest eigenvalue of each symmetric 3x3 matrix."""
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]


def local_frames(points: np.ndarray, camera: np.ndarray, *, k: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """Normals (PCA of the k nearest neighbours, facing `camera`) and axes of least
    curvature (PCA of the neighbours' normals), as GPD's local reference frames."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    kk = int(min(k, n))
    _, idx = cKDTree(points).query(points, k=kk)
    idx = np.asarray(idx).reshape(n, kk)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
    normals = _smallest_eigenvectors(np.einsum("nki,nkj->nij", nb, nb))
    flip = np.sum(normals * (camera - points), axis=1) < 0.0
    normals[flip] *= -1.0
    nn_ = normals[idx]
    # The normals of a curved patch spread across its axis of least curvature: that axis
    # is the direction they vary least along, the smallest eigenvector of their scatter.
    M = np.einsum("nki,nkj->nij", nn_, nn_)
    axes = _smallest_eigenvectors(M)
    return normals, axes


def cloud_from_depth(depth, *, fov_y_deg: float, X_WC, depth_min_m: float = 0.0,
                     depth_max_m: float = np.inf, center_xy=(0.5, 0.0),
                     workspace_half_m: float = 0.3, workspace_top_m: float = 0.4,
                     table_z: float = TABLE_TOP_Z_M, table_margin_m: float = 0.003,
                     voxel_m: float = 0.002, k: int = 15) -> Cloud:
    """The object cloud GPD works on (step 1 of the module docstring).

    Args:
        depth, fov_y_deg, X_WC, depth_min_m, depth_max_m: See `back_project`.
        center_xy, workspace_half_m, workspace_top_m: The workspace: a square of half
            side `workspace_half_m` about `center_xy`, up to `workspace_top_m` above the
            table (the gripper's own fingers, seen from above, lie beyond it).
        table_z, table_margin_m: Points below ``table_z + table_margin_m`` are the
            table and the sheet.
        voxel_m: Voxel side of the downsampled cloud [m].
        k: Neighbours of the normal and curvature estimates.
    """
    X = np.asarray(getattr(X_WC, "GetAsMatrix4", lambda: X_WC)(), dtype=float)
    P = back_project(depth, fov_y_deg=fov_y_deg, X_WC=X, depth_min_m=depth_min_m,
                     depth_max_m=depth_max_m)
    c = np.asarray(center_xy, dtype=float)
    keep = ((np.abs(P[:, 0] - c[0]) <= workspace_half_m) & (np.abs(P[:, 1] - c[1]) <= workspace_half_m)
            & (P[:, 2] >= table_z + table_margin_m) & (P[:, 2] <= workspace_top_m))
    P = voxel_downsample(P[keep], voxel_m)
    normals, axes = local_frames(P, X[:3, 3], k=k)
    return Cloud(P, normals, axes, X[:3, 3].copy())


# ----------------------------------------------------------------------------
# Candidates and geometric filters.


@dataclass(frozen=True)
class HandSearch:
    """GPD's candidate search (step 2) and geometric filters (step 3)."""

    num_samples: int = 300
    num_rotations: int = 8
    depths: tuple = DEFAULT_DEPTHS_M
    approach_max_tilt_deg: float = 30.0
    # Cloud spacing of the collision samples [m] (the fine set is the cloud itself).
    collision_voxel_m: float = 0.004
    min_points_between: int = 10
    min_width_m: float = 0.005
    table_clearance_m: float = 0.002


def _perpendicular_basis(approach: np.ndarray) -> np.ndarray:
    ref = np.tile([1.0, 0.0, 0.0], (len(approach), 1))
    ref[np.abs(approach[:, 0]) > 0.9] = [0.0, 1.0, 0.0]
    e1 = ref - np.sum(ref * approach, axis=1, keepdims=True) * approach
    return e1 / np.linalg.norm(e1, axis=1, keepdims=True)


def _into_cone(direction: np.ndarray, max_tilt_rad: float) -> np.ndarray:
    """Each unit vector pulled (in its vertical plane) to within `max_tilt_rad` of -z."""
    down = np.array([0.0, 0.0, -1.0])
    cos_t = np.clip(-direction[:, 2], -1.0, 1.0)
    tilt = np.arccos(cos_t)
    horiz = direction[:, :2]
    h = np.linalg.norm(horiz, axis=1)
    az = np.where(h > 1e-9, np.arctan2(horiz[:, 1], horiz[:, 0]), 0.0)
    t = np.minimum(tilt, max_tilt_rad)
    out = np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)], axis=1)
    return np.where((h > 1e-9)[:, None], out, down)


@dataclass(frozen=True)
class Hands:
    """Hand candidates that pass the geometric filters.

    Attributes:
        poses: (N, 4, 4) grasp-frame poses X_WG.
        width: (N,) extent of the cloud points between the pads along x_G [m].
        num_points: (N,) cloud points in the closing region.
    """

    poses: np.ndarray
    width: np.ndarray
    num_points: np.ndarray

    def __len__(self) -> int:
        return len(self.poses)


def sample_hands(cloud: Cloud, rng: np.random.Generator, search: HandSearch = HandSearch()) -> Hands:
    """GPD's candidates on the cloud, kept where the geometric filters pass."""
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    empty = Hands(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))
    if len(cloud) < search.min_points_between:
        return empty
    S = min(int(search.num_samples), len(cloud))
    pick = rng.choice(len(cloud), size=S, replace=False)
    origins = cloud.points[pick]
    tilt = np.deg2rad(search.approach_max_tilt_deg)
    # Two approaches per sample: straight down and against the normal, within the cone.
    along_normal = _into_cone(-cloud.normals[pick], tilt)
    approach = np.concatenate([np.tile([0.0, 0.0, -1.0], (S, 1)), along_normal])
    origins = np.concatenate([origins, origins])
    axes = np.concatenate([cloud.axes[pick], cloud.axes[pick]])
    e1 = _perpendicular_basis(approach)
    e2 = np.cross(approach, e1)
    # The first closing direction runs across the axis of least curvature (around a
    # cylinder, not along it), in the plane across the approach.
    across = np.cross(axes, approach)
    ok = np.linalg.norm(across, axis=1) > 0.3
    base = np.where(ok, np.arctan2(np.sum(across * e2, axis=1), np.sum(across * e1, axis=1)),
                    rng.uniform(0.0, np.pi, len(origins)))
    fine = ScenePoints(cloud.points, cloud.normals, np.zeros(len(cloud), dtype=np.int64))
    coarse_pts = voxel_downsample(cloud.points, search.collision_voxel_m)
    coarse = ScenePoints(coarse_pts, np.zeros_like(coarse_pts), np.zeros(len(coarse_pts), dtype=np.int64))
    ev = evaluate_hands(fine, coarse, origins, approach, e1, np.mod(base, np.pi),
                        int(search.num_rotations), np.asarray(search.depths, float),
                        table_clearance_m=search.table_clearance_m)
    keep = (ev.collision_free & (ev.num_points_between >= search.min_points_between)
            & (ev.width >= search.min_width_m) & (ev.width <= STROKE_M))
    poses, (s, kk, d) = evaluation_poses(ev, approach, keep)
    return Hands(poses, ev.width[s, kk, d].astype(float), ev.num_points_between[s, kk, d])


# ----------------------------------------------------------------------------
# Grasp images.


def grasp_images(cloud: Cloud, poses: np.ndarray, *, size: int = IMAGE_SIZE,
                 half_m: float = REGION_HALF_M, chunk: int = 256) -> np.ndarray:
    """GPD's 15-channel grasp images (float32, (N, 15, size, size), values in [0, 1]).

    The cloud points inside the cube |x|, |y|, |z| <= `half_m` of each hand frame,
    projected along z_G (onto the x-y plane: what the hand sees coming in), along y_G
    (x-z: the closing plane side on) and along x_G (y-z: through the pads). Per
    projection: occupancy; the hand-frame normal of the point nearest the viewer
    ((n + 1) / 2, 3 channels); its depth (1 nearest, toward 0 at the far side).
    """
    from scipy.spatial import cKDTree

    X = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    N = len(X)
    out = np.zeros((N, CHANNELS, size, size), np.float32)
    if N == 0 or len(cloud) == 0:
        return out
    tree = cKDTree(cloud.points)
    R = X[:, :3, :3]
    t = X[:, :3, 3]
    # (projection axis, image row axis, image column axis) in hand coordinates.
    views = ((2, 0, 1), (1, 0, 2), (0, 1, 2))
    for lo in range(0, N, chunk):
        hi = min(N, lo + chunk)
        lists = tree.query_ball_point(t[lo:hi], r=half_m * np.sqrt(3.0))
        arrays = [np.asarray(x, dtype=np.int64) for x in lists]
        counts = np.array([len(a) for a in arrays], dtype=np.int64)
        if counts.sum() == 0:
            continue
        # Hand coordinates, one small product per hand (cheaper than gathering a
        # rotation per point).
        ps, ns, owners = [], [], []
        for j, ids in enumerate(arrays):
            if len(ids) == 0:
                continue
            Rj = R[lo + j]
            q = (cloud.points[ids] - t[lo + j]) @ Rj
            inside = np.all(np.abs(q) <= half_m, axis=1)
            ps.append(q[inside])
            ns.append(cloud.normals[ids[inside]] @ Rj)
            owners.append(np.full(int(inside.sum()), j, dtype=np.int64))
        p, n, owner = np.concatenate(ps), np.concatenate(ns), np.concatenate(owners)
        cell = np.clip(((p + half_m) / (2.0 * half_m) * size).astype(np.int64), 0, size - 1)
        depth = (p + half_m) / (2.0 * half_m)  # 0 nearest the viewer along +axis
        for v, (axis, row, col) in enumerate(views):
            flat = (owner * size + cell[:, row]) * size + cell[:, col]
            # Nearest point per pixel: sort by (pixel, depth), keep each pixel's first.
            key = (flat << 21) + np.round(depth[:, axis] * (1 << 20)).astype(np.int64)
            order = np.argsort(key, kind="stable")
            f_sorted = flat[order]
            first = np.ones(len(order), dtype=bool)
            first[1:] = f_sorted[1:] != f_sorted[:-1]
            sel = order[first]
            o, r, c = owner[sel] + lo, cell[sel, row], cell[sel, col]
            base = 5 * v
            out[o, base, r, c] = 1.0
            for j in range(3):
                out[o, base + 1 + j, r, c] = 0.5 * (n[sel, j] + 1.0)
            out[o, base + 4, r, c] = 1.0 - depth[sel, axis]
    return out


# ----------------------------------------------------------------------------
# Classifier.


class GraspClassifier(nn.Module):
    """GPD's LeNet on 15-channel grasp images: logit of "this candidate is a grasp"."""

    def __init__(self, size: int = IMAGE_SIZE):
        super().__init__()
        self.size = int(size)
        s = ((self.size - 4) // 2 - 4) // 2
        self.features = nn.Sequential(
            nn.Conv2d(CHANNELS, 20, 5), nn.MaxPool2d(2),
            nn.Conv2d(20, 50, 5), nn.MaxPool2d(2))
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(50 * s * s, 500), nn.ReLU(),
                                  nn.Dropout(0.5), nn.Linear(500, 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(images)).squeeze(-1)

    @torch.no_grad()
    def probabilities(self, images: np.ndarray, batch: int = 512) -> np.ndarray:
        self.eval()
        out = [torch.sigmoid(self(torch.from_numpy(np.ascontiguousarray(images[i:i + batch]))))
               for i in range(0, len(images), batch)]
        return torch.cat(out).numpy().astype(float) if out else np.zeros(0)


class ClassifierEnsemble(nn.Module):
    """Several `GraspClassifier`s whose probabilities are averaged (`probabilities`).

    Classifiers trained on different data err on different candidates. On dev piles the
    mean of two ranked a true grasp first more often than either alone; in the clutter
    experiment it grasped as often as one (models/gpd/README.md has the numbers). Saved
    and loaded as one safetensors file (`save_classifier`, `load_classifier`), so a run's
    identity is still one file's sha256.
    """

    def __init__(self, members):
        super().__init__()
        members = list(members)
        if len(members) < 2:
            raise ValueError(f"ClassifierEnsemble: expected at least 2 classifiers, got {len(members)}")
        sizes = {m.size for m in members}
        if len(sizes) != 1:
            raise ValueError(f"ClassifierEnsemble: the classifiers' image sizes differ: {sorted(sizes)}")
        self.members = nn.ModuleList(members)
        self.size = members[0].size

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """The logit of the mean probability (so that sigmoid(forward) = `probabilities`)."""
        p = torch.stack([torch.sigmoid(m(images)) for m in self.members]).mean(dim=0)
        return torch.logit(p, eps=1e-7)

    @torch.no_grad()
    def probabilities(self, images: np.ndarray, batch: int = 512) -> np.ndarray:
        return np.mean([m.probabilities(images, batch) for m in self.members], axis=0)


def save_classifier(model: GraspClassifier | ClassifierEnsemble, path: str | Path, *,
                    metadata: dict | None = None) -> None:
    """Writes the weights as safetensors (no code can run on load), atomically.

    An ensemble is one file: its members' tensors under `members.<i>.`, and "members" in
    the header.
    """
    import safetensors.torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": WEIGHTS_FORMAT, "image_size": str(model.size)}
    if isinstance(model, ClassifierEnsemble):
        meta["members"] = str(len(model.members))
    meta.update({k: str(v) for k, v in (metadata or {}).items()})
    tmp = path.with_name(path.name + ".tmp")
    safetensors.torch.save_file({k: v.contiguous() for k, v in model.state_dict().items()},
                                str(tmp), metadata=meta)
    tmp.replace(path)


def default_weights_path() -> Path:
    from drake_grasp.core.assets import models_dir

    return Path(models_dir()) / "gpd" / "weights.safetensors"


def load_classifier(path: str | Path = "") -> GraspClassifier | ClassifierEnsemble:
    """The classifier from a safetensors file ("" = the shipped models/gpd weights): one
    `GraspClassifier`, or a `ClassifierEnsemble` when the file holds several.

    Raises:
        FileNotFoundError / ValueError: naming the file and what was expected.
    """
    import safetensors
    import safetensors.torch

    path = Path(path) if path else default_weights_path()
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no GPD classifier weights (train them with `drake-grasp gpd-train`)")
    with safetensors.safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
    if meta.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{path}: not GPD classifier weights (metadata format "
                         f"{meta.get('format')!r}, expected {WEIGHTS_FORMAT!r})")
    size = int(meta.get("image_size", IMAGE_SIZE))
    members = meta.get("members")
    if members is None:
        model = GraspClassifier(size)
    else:
        if not members.isdigit() or int(members) < 2:
            raise ValueError(f"{path}: header 'members' is {members!r}, expected an integer >= 2")
        model = ClassifierEnsemble(GraspClassifier(size) for _ in range(int(members)))
    try:
        model.load_state_dict(safetensors.torch.load_file(str(path)))
    except RuntimeError as e:
        raise ValueError(f"{path}: weights do not fit the classifier: {e}") from None
    model.eval()
    return model


def combine_classifiers(paths, out: str | Path) -> ClassifierEnsemble:
    """Writes the `ClassifierEnsemble` of the classifiers in `paths` (single classifiers
    or ensembles, flattened) to `out`, with each source's sha256 in the header."""
    from drake_grasp.core.provenance import file_sha256

    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise ValueError(f"combine_classifiers: expected at least 2 weights files, got {len(paths)}")
    members = []
    for p in paths:
        m = load_classifier(p)
        members.extend(m.members if isinstance(m, ClassifierEnsemble) else [m])
    model = ClassifierEnsemble(members)
    save_classifier(model, out, metadata={
        "sources": ",".join(f"{p.name}:{file_sha256(p)}" for p in paths)})
    return model


# ----------------------------------------------------------------------------
# Selection and the detector.




@dataclass
class GpdDetector:
    """The whole pipeline: depth image -> selected grasps (`detect`)."""

    classifier: GraspClassifier | ClassifierEnsemble
    fov_y_deg: float
    depth_min_m: float
    depth_max_m: float
    center_xy: tuple = (0.5, 0.0)
    search: HandSearch = field(default_factory=HandSearch)
    selection: Selection = field(default_factory=Selection)

    def detect(self, depth, X_WC, rng: np.random.Generator) -> Detections:
        timings: dict = {}
        t0 = time.perf_counter()
        cloud = cloud_from_depth(depth, fov_y_deg=self.fov_y_deg, X_WC=X_WC,
                                 depth_min_m=self.depth_min_m, depth_max_m=self.depth_max_m,
                                 center_xy=self.center_xy)
        t1 = time.perf_counter()
        hands = sample_hands(cloud, rng, self.search)
        t2 = time.perf_counter()
        images = grasp_images(cloud, hands.poses)
        t3 = time.perf_counter()
        prob = self.classifier.probabilities(images) if len(images) else np.zeros(0)
        t4 = time.perf_counter()
        order = select(hands.poses, prob, self.selection)
        t5 = time.perf_counter()
        timings.update(cloud=t1 - t0, candidates=t2 - t1, images=t3 - t2, classifier=t4 - t3,
                       selection=t5 - t4)
        return Detections(hands.poses[order], prob[order], len(hands), len(cloud), timings)


def make_detector(scenario, classifier: GraspClassifier | ClassifierEnsemble | None = None):
    """detect(depth, X_WC) -> X_WG (4x4) of the selected grasp, or None, for a scenario.

    The classifier is `scenario.gpd.weights` ("" = shipped) unless one is given; the
    candidate search's randomness comes from the scenario's seed.
    """
    g = scenario.gpd
    model = classifier if classifier is not None else load_classifier(g.weights)
    detector = GpdDetector(model, fov_y_deg=g.fov_y_deg, depth_min_m=g.depth_min_m,
                           depth_max_m=g.depth_max_m,
                           center_xy=tuple(float(v) for v in scenario.scene.center_xy_m),
                           search=HandSearch(approach_max_tilt_deg=g.approach_max_tilt_deg),
                           selection=Selection(fallback=g.fallback_best))

    failed = scenario.failure_memory.failed()

    def detect(depth, X_WC):
        rng = np.random.default_rng([int(scenario.seed), 59])
        return detector.detect(depth, X_WC, rng).best(failed, scenario.failure_memory.radius_m)

    detect.detector = detector
    return detect
