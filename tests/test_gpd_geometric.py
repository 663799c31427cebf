"""One-shot grasp pose detection from one depth image (the paper's GPD baseline).

Most tests ray-cast synthetic depth images in numpy with the wrist camera's pinhole
model (no Drake); one renders a real scene with Drake and checks the best detection
against the ground-truth grasp tests of `drake_grasp.geometry.grasps`.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from drake_grasp.policies.gpd_geometric import best_grasp, detect_grasps
from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.policies.gpd_geometric_cloud import depth_to_points, remove_table
from drake_grasp.policies.gpd_geometric_results import DetectedGrasps, ScoreWeights
from drake_grasp.geometry.contact_physics import force_closure
from drake_grasp.geometry.grasp_metric import angle_difference_deg
from drake_grasp.geometry.hand_checks import check_grasp_poses
from drake_grasp.geometry.hand_model import TABLE_TOP_Z_M, topdown_rotation
from drake_grasp.geometry.scene_samples import sample_scene_points

FOV_Y_DEG = 55.0
SIZE = 64
FAR = 1.5
# Camera in the grasp frame (`station.gripper_frame_offsets()[2]`, checked against
# the gripper model in the Drake test below): 5 cm off the grasp axis, 11.5 cm behind.
X_GC = np.eye(4)
X_GC[:3, 3] = [0.0, -0.05, -0.115]
BOX_EXTENTS = (0.05, 0.12, 0.04)  # lying on the sheet: only the 5 cm side fits the hand


def _hand_pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = topdown_rotation(np.deg2rad(yaw_deg))
    X[:3, 3] = [x, y, z]
    return X


def _camera(x: float = 0.5, y: float = 0.0, height: float = 0.3, yaw_deg: float = 0.0):
    """X_WC of the wrist camera `height` above the table, hand at (x, y, yaw)."""
    return _hand_pose(x, y, height + X_GC[2, 3], yaw_deg) @ X_GC


def _render(X_WC, *, boxes=(), spheres=()) -> np.ndarray:
    """Ray-cast depth (along the optical axis, as Drake renders) of the sheet and of
    boxes ((centre xy, extents, yaw_deg), standing on the sheet) and spheres
    ((centre xyz, radius)); float32, far pixels at FAR."""
    camera = PinholeCamera.from_fov(SIZE, SIZE, FOV_Y_DEG)
    f, cu, cv = camera.focal_px, camera.cu, camera.cv
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    ray_C = np.stack([(u - cu) / f, (v - cv) / f, np.ones((SIZE, SIZE))], axis=-1)
    ray = ray_C @ X_WC[:3, :3].T  # z_C = 1: the ray parameter is the depth
    o = X_WC[:3, 3]
    t = np.full((SIZE, SIZE), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_sheet = (TABLE_TOP_Z_M - o[2]) / ray[..., 2]
        t = np.where(t_sheet > 0, t_sheet, t)
        for (cx, cy), ext, yaw_deg in boxes:
            c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
            R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            centre = np.array([cx, cy, TABLE_TOP_Z_M + 0.5 * ext[2]])
            o_B, ray_B = R.T @ (o - centre), ray @ R  # rays in the box frame
            half = 0.5 * np.asarray(ext)
            t1, t2 = (-half - o_B) / ray_B, (half - o_B) / ray_B
            t_in = np.minimum(t1, t2).max(axis=-1)
            t_out = np.maximum(t1, t2).min(axis=-1)
            hit = (t_in <= t_out) & (t_in > 0) & (t_in < t)
            t = np.where(hit, t_in, t)
        for centre, radius in spheres:
            oc = o - np.asarray(centre)
            b = ray @ oc
            a = np.sum(ray * ray, axis=-1)
            disc = b * b - a * (oc @ oc - radius**2)
            t_s = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            hit = (disc >= 0) & (t_s > 0) & (t_s < t)
            t = np.where(hit, t_s, t)
    return np.where(np.isfinite(t), t, FAR).astype(np.float32)


def _box_mesh(xy, extents, yaw_deg: float = 0.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.deg2rad(yaw_deg), [0, 0, 1]))
    mesh.apply_translation([xy[0], xy[1], TABLE_TOP_Z_M + 0.5 * extents[2]])
    return mesh


def _detect(depth, X_WC, seed: int = 0, **kwargs) -> DetectedGrasps:
    return detect_grasps(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC, rng=np.random.default_rng(seed),
                         **kwargs)


# ----------------------------------------------------------------------------
# Point cloud.


def test_points_and_normals_of_the_bare_sheet():
    X_WC = _camera()
    depth = _render(X_WC)
    points, normals = depth_to_points(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC)
    assert points.shape == normals.shape == (SIZE * SIZE, 3)
    np.testing.assert_allclose(points[:, 2], TABLE_TOP_Z_M, atol=1e-5)
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (len(normals), 1)), atol=1e-4)
    # The optical axis (between the four centre pixels) meets the sheet under the camera.
    centre = points.reshape(SIZE, SIZE, 3)[SIZE // 2 - 1:SIZE // 2 + 1, SIZE // 2 - 1:SIZE // 2 + 1]
    np.testing.assert_allclose(centre.reshape(-1, 3).mean(axis=0)[:2], X_WC[:2, 3], atol=1e-9)
    # Nothing of the sheet survives the table cut.
    assert not remove_table(points).any()


def test_far_and_invalid_pixels_are_dropped():
    X_WC = _camera()
    depth = _render(X_WC)
    depth[:5] = FAR  # nothing within range
    depth[10, :7] = 0.0  # no reading
    depth[20, :3] = np.inf  # Drake's "beyond the far clip"
    points, normals = depth_to_points(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC)
    assert len(points) == len(normals) == SIZE * SIZE - 5 * SIZE - 7 - 3
    assert np.all(np.isfinite(points)) and np.all(np.isfinite(normals))


def test_box_points_lie_on_the_box_and_normals_face_the_camera():
    X_WC = _camera()
    depth = _render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 0.0)])
    points, normals = depth_to_points(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC)
    top = points[:, 2] > TABLE_TOP_Z_M + 0.039
    assert top.sum() > 150  # 5 x 12 cm at ~4 mm per pixel
    inside = np.clip(points[top, :2], [0.475, -0.06], [0.525, 0.06])
    np.testing.assert_allclose(points[top, :2], inside, atol=1e-9)
    # All normals point toward the camera.
    assert np.all(np.sum(normals * (X_WC[:3, 3] - points), axis=1) > 0)


# ----------------------------------------------------------------------------
# Detection on synthetic scenes.


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 117.0])
def test_box_is_grasped_across_its_narrow_side(yaw_deg):
    X_WC = _camera()
    depth = _render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, yaw_deg)])
    grasps = _detect(depth, X_WC)
    assert len(grasps) > 10
    best = grasps.best()
    # Closing along the box's 5 cm side (its x axis, at `yaw_deg`).
    assert angle_difference_deg(best.xy_theta[2], yaw_deg) <= 15.0
    assert np.hypot(best.xy_theta[0] - 0.5, best.xy_theta[1]) <= 0.015
    assert best.width == pytest.approx(0.05, abs=0.006)
    # Fingertips (19 mm below the centre) at least 4 mm above the table top (z = 0),
    # as `check_grasp_poses` demands of them (2 mm over the 2 mm sheet).
    assert 0.004 + 0.019 - 1e-9 <= best.z <= TABLE_TOP_Z_M + 0.04
    # An antipodal grasp of the true box by the ground-truth tests.
    box = _box_mesh((0.5, 0.0), BOX_EXTENTS, yaw_deg)
    check = check_grasp_poses(best.pose, sample_scene_points([box], np.random.default_rng(0)))
    assert check.valid.tolist() == [True]
    # Every detection passed the antipodal test on what the camera saw; by the true
    # geometry all are collision-free, the top ten valid, and most of the others
    # (those near the friction cone's edge are at the mercy of a pixel).
    assert np.all(grasps.width <= 0.085)
    assert np.all(force_closure(grasps.contacts[:, 0], grasps.contact_normals[:, 0],
                                grasps.contacts[:, 1], grasps.contact_normals[:, 1], mu=0.5))
    truth = check_grasp_poses(grasps.poses(), sample_scene_points([box], np.random.default_rng(0)))
    assert np.all(truth.collision_free)
    assert np.all(truth.valid[:10]) and truth.valid.mean() >= 0.8


def test_result_layout():
    X_WC = _camera()
    grasps = _detect(_render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 20.0)]), X_WC)
    n = len(grasps)
    assert n > 0
    assert grasps.xy_theta.shape == (n, 3) and grasps.z.shape == grasps.width.shape == (n,)
    assert grasps.contacts.shape == grasps.contact_normals.shape == (n, 2, 3)
    assert np.all((grasps.xy_theta[:, 2] >= 0.0) & (grasps.xy_theta[:, 2] < 180.0))
    assert np.all(np.diff(grasps.score) <= 0.0)
    # The score is the weighted sum of its terms, each in [0, 1].
    w = ScoreWeights()
    total = sum(getattr(w, k) * v for k, v in grasps.terms.items())
    np.testing.assert_allclose(total, grasps.score)
    assert all(np.all((v >= 0.0) & (v <= 1.0)) for v in grasps.terms.values())
    # Poses: top-down (z_G down), x_G at theta, the contacts along -x_G then +x_G.
    X = grasps.poses()
    np.testing.assert_allclose(X[:, :3, 2], np.tile([0.0, 0.0, -1.0], (n, 1)), atol=1e-12)
    th = np.deg2rad(grasps.xy_theta[:, 2])
    np.testing.assert_allclose(X[:, :2, 0], np.column_stack([np.cos(th), np.sin(th)]), atol=1e-12)
    along = np.sum((grasps.contacts[:, 1] - grasps.contacts[:, 0]) * X[:, :3, 0], axis=1)
    assert np.all(along > 0)
    np.testing.assert_allclose(X[0], grasps.best().pose)
    np.testing.assert_allclose(grasps.hand_poses()[0], grasps.best().hand_pose)


def test_sphere_wider_than_the_stroke_has_no_grasp():
    X_WC = _camera()
    depth = _render(X_WC, spheres=[((0.5, 0.0, TABLE_TOP_Z_M + 0.05), 0.05)])
    assert len(_detect(depth, X_WC)) == 0
    assert best_grasp(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC, rng=np.random.default_rng(1)) is None


def test_small_sphere_is_grasped_across_its_middle():
    X_WC = _camera()
    depth = _render(X_WC, spheres=[((0.5, 0.0, TABLE_TOP_Z_M + 0.03), 0.03)])
    best = best_grasp(depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC, rng=np.random.default_rng(0))
    assert best is not None
    assert np.hypot(best.xy_theta[0] - 0.5, best.xy_theta[1]) <= 0.01
    assert best.width == pytest.approx(0.06, abs=0.006)


def test_empty_table_has_no_grasp():
    X_WC = _camera()
    grasps = _detect(_render(X_WC), X_WC)
    assert len(grasps) == 0 and grasps.best() is None
    assert grasps.xy_theta.shape == (0, 3)


def test_fingers_may_not_land_on_a_neighbour():
    # A tall block 45 mm beside the box's long side, where a finger closing across
    # the box would go: no detection may put a finger over it.
    X_WC = _camera()
    block = ((0.5 + 0.05, 0.0), (0.02, 0.03, 0.08), 0.0)
    depth = _render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 0.0), block])
    grasps = _detect(depth, X_WC)
    meshes = [_box_mesh((0.5, 0.0), BOX_EXTENTS), _box_mesh(*block)]
    check = check_grasp_poses(grasps.poses(), sample_scene_points(meshes, np.random.default_rng(0)))
    assert np.all(check.collision_free)
    assert check.valid[0]
    # The box is still grasped, away from the block.
    on_box = np.abs(grasps.xy_theta[:, 0] - 0.5) < 0.02
    assert on_box.any()
    assert np.all(np.abs(grasps.xy_theta[on_box, 1]) >= 0.015 - 1e-9)


def test_same_seed_same_detections_and_other_seeds_agree():
    X_WC = _camera()
    depth = _render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 10.0)])
    a, b = _detect(depth, X_WC, seed=3), _detect(depth, X_WC, seed=3)
    for key in ("xy_theta", "z", "width", "score", "contacts", "contact_normals"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    for seed in (4, 5):
        other = _detect(depth, X_WC, seed=seed).best()
        assert angle_difference_deg(other.xy_theta[2], 10.0) <= 15.0
        assert np.hypot(other.xy_theta[0] - 0.5, other.xy_theta[1]) <= 0.015


def test_stats_count_the_stages():
    X_WC = _camera()
    stats: dict = {}
    grasps = _detect(_render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 0.0)]), X_WC, stats=stats)
    stages = ["hands", "collision_free", "closing_region", "antipodal", "in_view", "visible"]
    counts = [stats[k] for k in stages]
    assert counts == sorted(counts, reverse=True) and counts[-1] == len(grasps)
    assert stats["samples"] == min(200, stats["points"]) and stats["seconds"] > 0


def test_occlusion_check_keeps_clear_grasps():
    X_WC = _camera()
    depth = _render(X_WC, boxes=[((0.5, 0.0), BOX_EXTENTS, 0.0)])
    plain, strict = _detect(depth, X_WC), _detect(depth, X_WC, occlusion_check=True)
    assert 0 < len(strict) <= len(plain)
    assert angle_difference_deg(strict.best().xy_theta[2], 0.0) <= 15.0


# ----------------------------------------------------------------------------
# Arguments.


def test_bad_arguments_are_named():
    X_WC = _camera()
    depth = _render(X_WC)
    rng = np.random.default_rng(0)

    def detect(**kw):
        args = dict(depth=depth, fov_y_deg=FOV_Y_DEG, X_WC=X_WC, rng=rng)
        args.update(kw)
        return detect_grasps(args.pop("depth"), **args)

    nan = depth.copy()
    nan[3, 4] = np.nan
    cases = [
        (dict(depth=depth[0]), "depth"),
        (dict(depth=np.stack([depth] * 3, axis=-1)), "depth"),
        (dict(depth=nan), "depth.*NaN"),
        (dict(depth=np.full((2, 2), 0.3)), "depth"),
        (dict(X_WC=X_WC[:3]), "X_WC"),
        (dict(X_WC=np.diag([1.0, 1.0, 2.0, 1.0])), "X_WC"),
        (dict(X_WC=np.where(np.eye(4) > 0, np.nan, 0.0)), "X_WC"),
        (dict(rng=0), "rng"),
        (dict(fov_y_deg=0.0), "fov_y_deg"),
        (dict(fov_y_deg=float("nan")), "fov_y_deg"),
        (dict(mu=-0.1), "mu"),
        (dict(num_samples=0), "num_samples"),
        (dict(num_rotations=2.5), "num_rotations"),
        (dict(depths=[-0.01]), "depths"),
        (dict(depths=[]), "depths"),
        (dict(table_z=float("inf")), "table_z"),
        (dict(weights={"antipodal": 1.0}), "weights"),
        (dict(weights=ScoreWeights(view=-1.0)), "weights.view"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ValueError, match=match):
            detect(**kwargs)
    with pytest.raises(ValueError, match="X_WC"):
        depth_to_points(depth, fov_y_deg=FOV_Y_DEG, X_WC=np.eye(3))
    with pytest.raises(ValueError, match="points"):
        remove_table(np.zeros((4, 2)))


# ----------------------------------------------------------------------------
# A real rendered scene (Drake).


def test_rendered_tetra_pak_best_detection_is_a_true_grasp(library):
    pytest.importorskip("pydrake")
    from drake_grasp.learning.dataset import SceneRenderer
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.geometry.scene_samples import scene_meshes
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import build_scene_world, make_scene
    from drake_grasp.geometry.sensing import postprocess_depth
    from drake_grasp.world.station import gripper_frame_offsets, topdown_pose

    np.testing.assert_allclose(gripper_frame_offsets()[2].GetAsMatrix4(), X_GC, atol=1e-9)
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{scene: {object_ids: [tetra_pak_000], pose: lying}}")
    settled = make_scene(scenario.scene, 0, library)
    renderer = SceneRenderer(build_scene_world(settled, library, renderer_name="vtk"),
                             scenario.camera)
    hand = np.array([0.5, 0.0, 0.185, 0.0])  # camera 0.3 m above the table
    raw = renderer.render(hand)
    depth = postprocess_depth(raw, None, scenario.depth_noise, scenario.camera.depth_max_m)
    X_WC = (topdown_pose(hand[:2], hand[2], 0.0) @ renderer.X_GC).GetAsMatrix4()
    best = best_grasp(depth, fov_y_deg=scenario.camera.fov_y_deg, X_WC=X_WC,
                      rng=np.random.default_rng(0), max_depth_m=scenario.camera.depth_max_m)
    assert best is not None
    scene = sample_scene_points(scene_meshes(settled, library), np.random.default_rng(0))
    valid = bool(check_grasp_poses(best.pose, scene).valid[0])
    if not valid:  # else it must be next to a ground-truth grasp
        truth = find_grasps(settled, library, np.random.default_rng(0))
        near = (np.hypot(*(truth.xy_theta[:, :2] - best.xy_theta[:2]).T) <= 0.02) & (
            angle_difference_deg(truth.xy_theta[:, 2], best.xy_theta[2]) <= 15.0)
        assert near.any(), distance_to_nearest_grasp(best.xy_theta[None], truth.xy_theta)
