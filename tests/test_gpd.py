"""The learned GPD baseline's pipeline (drake_grasp.policies.gpd), without Drake."""

import numpy as np
import pytest
import torch
import trimesh

from drake_grasp.policies import gpd, gpd_ranking
from drake_grasp.geometry.hand_model import TABLE_TOP_Z_M, topdown_rotation


def _view(height=0.6, xy=(0.5, 0.0)):
    X = np.eye(4)
    X[:3, :3] = topdown_rotation(0.0)
    X[:3, 3] = [xy[0], xy[1], height]
    return X


def _render(mesh: trimesh.Trimesh, X_WC, H=120, W=160, fov_y_deg=45.0):
    """Depth of `mesh` over a table at z = 0 by ray casting (Drake's pinhole model)."""
    f = 0.5 * H / np.tan(np.deg2rad(fov_y_deg) / 2)
    v, u = np.mgrid[0:H, 0:W]
    d_C = np.stack([(u - (W / 2 - 0.5)) / f, (v - (H / 2 - 0.5)) / f, np.ones_like(u, float)], -1)
    d_C = d_C.reshape(-1, 3)
    R, t = X_WC[:3, :3], X_WC[:3, 3]
    dirs = d_C @ R.T
    # The table plane z = 0 first, then the object where it is nearer.
    depth = (0.0 - t[2]) / dirs[:, 2]
    locs, ray, _ = mesh.ray.intersects_location(np.tile(t, (len(dirs), 1)), dirs, multiple_hits=False)
    hit = ((locs - t) @ R)[:, 2]
    depth[ray] = np.minimum(depth[ray], hit)
    return depth.reshape(H, W).astype(np.float32)


def _box_scene(size=(0.05, 0.12, 0.06), xy=(0.5, 0.0)):
    box = trimesh.creation.box(extents=size)
    box.apply_translation([xy[0], xy[1], size[2] / 2 + TABLE_TOP_Z_M])
    return box


def test_back_project_drops_invalid_and_places_points():
    X = _view(0.6)
    depth = np.full((6, 8), 0.6, np.float32)
    depth[0, 0] = 0.0
    depth[1, 1] = np.inf
    depth[2, 2] = np.nan
    P = gpd.back_project(depth, fov_y_deg=45.0, X_WC=X, depth_min_m=0.4, depth_max_m=3.5)
    assert len(P) == 6 * 8 - 3
    np.testing.assert_allclose(P[:, 2], 0.0, atol=1e-6)  # the camera looks straight down (float32 depth)
    with pytest.raises(ValueError, match="depth"):
        gpd.back_project(np.zeros(5), fov_y_deg=45.0, X_WC=X, depth_min_m=0.4, depth_max_m=3.5)
    with pytest.raises(ValueError, match="X_WC"):
        gpd.back_project(depth, fov_y_deg=45.0, X_WC=np.eye(3), depth_min_m=0.4, depth_max_m=3.5)


def test_cloud_removes_table_and_normals_face_camera():
    X = _view(0.6)
    box = _box_scene()
    depth = _render(box, X)
    cloud = gpd.cloud_from_depth(depth, fov_y_deg=45.0, X_WC=X, depth_min_m=0.4, depth_max_m=3.5)
    assert len(cloud) > 100
    assert cloud.points[:, 2].min() > TABLE_TOP_Z_M  # no table points
    top = cloud.points[:, 2] > 0.06
    assert top.sum() > 50
    # The box top's normals point up (toward the camera).
    assert np.median(cloud.normals[top, 2]) > 0.99


def test_curvature_axis_of_a_lying_cylinder_is_its_axis():
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.15, sections=64)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # axis along y
    cyl.apply_translation([0.5, 0.0, 0.03 + TABLE_TOP_Z_M])
    X = _view(0.5)
    cloud = gpd.cloud_from_depth(_render(cyl, X, H=240, W=320), fov_y_deg=45.0, X_WC=X,
                                 depth_min_m=0.3, depth_max_m=3.5)
    middle = np.abs(cloud.points[:, 1]) < 0.05
    along_y = np.abs(cloud.axes[middle, 1])
    assert np.median(along_y) > 0.9


def test_sample_hands_finds_collision_free_grasps_across_a_box():
    X = _view(0.6)
    box = _box_scene()
    cloud = gpd.cloud_from_depth(_render(box, X, H=240, W=320), fov_y_deg=45.0, X_WC=X,
                                 depth_min_m=0.4, depth_max_m=3.5)
    hands = gpd.sample_hands(cloud, np.random.default_rng(0), gpd.HandSearch(num_samples=100))
    assert len(hands) > 0
    z = hands.poses[:, :3, 2]
    # Every approach is within the 30 degree cone about straight down.
    assert np.all(-z[:, 2] >= np.cos(np.deg2rad(30.0)) - 1e-9)
    # Rotation blocks are proper rotations.
    R = hands.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (len(R), 1, 1)), atol=1e-9)
    # Some hands close across the 5 cm side (x_G along world x) near the box's middle.
    across = (np.abs(hands.poses[:, 0, 0]) > 0.95) & (np.abs(hands.poses[:, 1, 3]) < 0.03)
    assert across.any()
    assert np.all(hands.width <= 0.085)
    # The same seed gives the same hands.
    again = gpd.sample_hands(cloud, np.random.default_rng(0), gpd.HandSearch(num_samples=100))
    np.testing.assert_array_equal(hands.poses, again.poses)


def test_grasp_images_see_the_object_between_the_pads():
    X = _view(0.6)
    box = _box_scene()
    cloud = gpd.cloud_from_depth(_render(box, X, H=240, W=320), fov_y_deg=45.0, X_WC=X,
                                 depth_min_m=0.4, depth_max_m=3.5)
    on_box = np.eye(4)
    on_box[:3, :3] = topdown_rotation(0.0)
    on_box[:3, 3] = [0.5, 0.0, 0.05]
    far = on_box.copy()
    far[:3, 3] = [0.9, 0.4, 0.05]
    images = gpd.grasp_images(cloud, np.stack([on_box, far]))
    assert images.shape == (2, gpd.CHANNELS, gpd.IMAGE_SIZE, gpd.IMAGE_SIZE)
    assert images.dtype == np.float32
    assert images.min() >= 0.0 and images.max() <= 1.0
    assert images[0, 0].sum() > 50  # occupancy seen along the approach
    assert images[1].sum() == 0.0  # nothing there
    # The box's 5 cm width along x_G: occupied rows span about 5/8.5 of the image.
    rows = np.flatnonzero(images[0, 0].any(axis=1))
    assert 0.45 < (rows.max() - rows.min() + 1) / gpd.IMAGE_SIZE < 0.75


def test_selection_ranks_by_the_cluster_mean_probability():
    def pose(x, yaw_deg=0.0):
        X = np.eye(4)
        X[:3, :3] = topdown_rotation(np.deg2rad(yaw_deg))
        X[:3, 3] = [x, 0.0, 0.03]
        return X

    poses = np.stack([pose(0.0), pose(0.003), pose(0.006),   # a cluster of good ones
                      pose(0.3), pose(0.303, 90.0),          # confident, neighbour unlike it
                      pose(0.6), pose(0.603)])               # confident, neighbour weak
    prob = np.array([0.90, 0.92, 0.91, 0.99, 0.10, 0.97, 0.2])
    scores = gpd_ranking.cluster_scores(poses, prob)
    # The turned neighbour is not aligned with the confident one: it stands alone.
    assert scores[3] == pytest.approx(0.99)
    assert scores[5] == pytest.approx((0.97 + 0.2) / 2)
    order = gpd.select(poses, prob)
    assert order[0] == 3  # 0.99 alone
    assert list(order[1:4]) == [1, 2, 0] or set(order[1:4]) == {0, 1, 2}
    assert 4 not in order and 6 not in order  # below the threshold
    assert order[-1] == 5  # confident but its aligned neighbour is not
    assert len(gpd.select(poses, np.zeros(len(poses)))) == 0
    # With the fallback, none over the threshold ranks them all; otherwise it changes nothing.
    low = np.array([0.10, 0.12, 0.11, 0.3, 0.05, 0.2, 0.01])
    fallback = gpd.Selection(fallback=True)
    assert gpd.select(poses, low, fallback)[0] == 3 and len(gpd.select(poses, low, fallback)) == 7
    assert list(gpd.select(poses, prob, fallback)) == list(order)


def test_classifier_weights_round_trip_and_bad_files(tmp_path):
    torch.manual_seed(0)
    model = gpd.GraspClassifier()
    path = tmp_path / "w.safetensors"
    gpd.save_classifier(model, path)
    loaded = gpd.load_classifier(path)
    x = np.random.default_rng(0).random((4, gpd.CHANNELS, gpd.IMAGE_SIZE, gpd.IMAGE_SIZE)).astype(np.float32)
    np.testing.assert_allclose(loaded.probabilities(x), model.probabilities(x), rtol=1e-6)
    with pytest.raises(FileNotFoundError, match="gpd-train"):
        gpd.load_classifier(tmp_path / "missing.safetensors")
    import safetensors.torch

    other = tmp_path / "other.safetensors"
    safetensors.torch.save_file({"a": torch.zeros(1)}, str(other), metadata={"format": "x"})
    with pytest.raises(ValueError, match="not GPD classifier weights"):
        gpd.load_classifier(other)


def test_ensemble_averages_its_members_and_round_trips(tmp_path, capsys):
    """`gpd-combine` writes one file whose probabilities are the mean of its sources'; a
    combined file can be combined again (flattened), and bad inputs are refused."""
    from drake_grasp.cli.main import main

    x = np.random.default_rng(1).random((6, gpd.CHANNELS, gpd.IMAGE_SIZE, gpd.IMAGE_SIZE)).astype(np.float32)
    paths, probs = [], []
    for seed in (0, 1, 2):
        torch.manual_seed(seed)
        m = gpd.GraspClassifier()
        paths.append(tmp_path / f"m{seed}.safetensors")
        gpd.save_classifier(m, paths[-1])
        probs.append(m.probabilities(x))
    assert np.ptp(np.stack(probs), axis=0).max() > 1e-3  # the members differ
    pair = tmp_path / "pair.safetensors"
    assert main(["gpd-combine", str(paths[0]), str(paths[1]), "--out", str(pair)]) == 0
    assert "mean of 2 classifiers" in capsys.readouterr().out
    loaded = gpd.load_classifier(pair)
    assert isinstance(loaded, gpd.ClassifierEnsemble) and len(loaded.members) == 2
    np.testing.assert_allclose(loaded.probabilities(x), 0.5 * (probs[0] + probs[1]), rtol=1e-5)
    with torch.no_grad():  # forward is the mean's logit (what gpd_training's scoring calls)
        np.testing.assert_allclose(torch.sigmoid(loaded(torch.from_numpy(x))).numpy(),
                                   0.5 * (probs[0] + probs[1]), rtol=1e-5)
    trio = gpd.combine_classifiers([pair, paths[2]], tmp_path / "trio.safetensors")
    assert len(trio.members) == 3
    np.testing.assert_allclose(gpd.load_classifier(tmp_path / "trio.safetensors").probabilities(x),
                               np.mean(probs, axis=0), rtol=1e-5)
    # The detector takes either kind.
    detector = gpd.GpdDetector(loaded, fov_y_deg=45.0, depth_min_m=0.3, depth_max_m=1.5)
    assert detector.classifier.probabilities(x).shape == (6,)
    with pytest.raises(ValueError, match="at least 2"):
        gpd.combine_classifiers([paths[0]], tmp_path / "one.safetensors")
    assert not (tmp_path / "one.safetensors").exists()
    with pytest.raises(ValueError, match="image sizes differ"):
        gpd.ClassifierEnsemble([gpd.GraspClassifier(32), gpd.GraspClassifier(24)])
    import safetensors.torch

    bad = tmp_path / "bad.safetensors"
    safetensors.torch.save_file({k: v.contiguous() for k, v in loaded.state_dict().items()}, str(bad),
                                metadata={"format": "drake_grasp.gpd.GraspClassifier", "members": "1"})
    with pytest.raises(ValueError, match="'members' is '1'"):
        gpd.load_classifier(bad)


def test_shipped_classifier_loads():
    model = gpd.load_classifier()
    assert isinstance(model, gpd.ClassifierEnsemble) and len(model.members) == 2


def test_selection_variants_script_ranks_as_each_rule_says(analysis_script):
    """analysis/gpd_selection.py's variants on hand-made candidates: a lone grasp with the
    highest probability, a tight cluster of 3 (4 mm apart) with the largest sum, and a row
    of 5 grasps 15 mm apart that a second classifier prefers. Each rule picks its own."""
    module = analysis_script("gpd_selection")

    def pose(x, y):
        X = np.eye(4)
        X[:3, :3] = np.diag([1.0, -1.0, -1.0])  # approach straight down
        X[:3, 3] = [x, y, 0.05]
        return X

    poses = [pose(0.0, 0.0)]                                     # 0: lone, 0.99
    poses += [pose(0.2 + d, 0.0) for d in (0.0, 0.004, 0.008)]   # 1-3: tight, 0.95
    poses += [pose(0.4 + d, 0.0) for d in (0.0, 0.015, 0.03, 0.045, 0.06)]  # 4-8: loose
    prob = np.array([0.99, 0.95, 0.95, 0.95, 0.9, 0.9, 0.9, 0.9, 0.9])
    picks = module.variants(np.array(poses), prob, None)
    assert picks["shipped: highest probability"] == 0
    assert picks["shipped: cluster mean (the detector's)"] == 0  # a lone grasp's mean is its own
    assert picks["shipped: cluster sum (support)"] in (1, 2, 3)  # 3 x 0.95 beats 0.99 and 0.9
    assert picks["shipped: cluster mean, threshold 0.9"] == 0
    other = np.array([0.6, 0.6, 0.6, 0.6, 0.9, 0.9, 0.9, 0.9, 0.9])  # a second classifier
    picks = module.variants(np.array(poses), prob, other)
    assert picks["retrained: cluster mean"] in (4, 5, 6, 7, 8)
    # Means of both: lone 0.795, tight 0.775, loose 0.9.
    assert picks["mean of both: cluster mean"] in (4, 5, 6, 7, 8)
    assert module.variants(np.array(poses), np.zeros(9), None)["shipped: highest probability"] is None
