"""Ground-truth grasps of a scene (candidates, collisions, force closure) and the
paper's distance-to-nearest-grasp label."""

import numpy as np
import pytest
import trimesh

from drake_grasp.geometry.contact_physics import force_closure
from drake_grasp.geometry.grasp_candidates import sample_grasp_candidates
from drake_grasp.geometry.grasp_metric import (
    angle_difference_deg,
    distance_to_nearest_grasp,
    grasp_distance,
)
from drake_grasp.geometry.grasps import GraspSet, find_grasps, find_grasps_in_meshes
from drake_grasp.geometry.hand_checks import check_grasp_poses
from drake_grasp.geometry.hand_model import (
    FINGERTIP_Z_M,
    PAD_HALF_WIDTH_M,
    TABLE_TOP_Z_M,
    topdown_rotation,
)
from drake_grasp.geometry.scene_samples import (
    sample_scene_points,
    scene_meshes,
)

CLEARANCE = 0.002  # find_grasps_in_meshes' default table_clearance_m


def _on_table(mesh: trimesh.Trimesh, xy=(0.5, 0.0)) -> trimesh.Trimesh:
    mesh = mesh.copy()
    mesh.apply_translation([xy[0], xy[1], TABLE_TOP_Z_M - mesh.bounds[0, 2]])
    return mesh


def _box(extents, xy=(0.5, 0.0)) -> trimesh.Trimesh:
    return _on_table(trimesh.creation.box(extents=extents), xy)


def _topdown_pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = topdown_rotation(np.deg2rad(yaw_deg))
    X[:3, 3] = [x, y, z]
    return X


def _points(meshes, seed: int = 0):
    return sample_scene_points(meshes, np.random.default_rng(seed), spacing_m=0.003)


# ----------------------------------------------------------------------------
# Whole pipeline on hand-made objects.


def test_box_is_grasped_across_its_narrow_side_only():
    # 5 (x) x 12 (y) x 4 (z) cm lying on the table: only the 5 cm side fits the 85 mm stroke.
    box = _box((0.05, 0.12, 0.04))
    grasps = find_grasps_in_meshes([box], np.random.default_rng(0))
    assert len(grasps) > 20
    theta = grasps.xy_theta[:, 2]
    assert np.all((theta >= 0) & (theta < 180))
    # Closing along x (theta ~ 0 / 180), none along y (theta ~ 90).
    assert np.all(angle_difference_deg(theta, 0.0) <= 30.0)
    assert np.all(grasps.widths >= 0.049) and np.all(grasps.widths <= 0.06)
    # Centres over the box, the fingers clear of it (|x - 0.5| <= 42.5 - 25 mm).
    assert np.all(np.abs(grasps.xy_theta[:, 0] - 0.5) <= 0.0175 + 0.003)
    assert np.all(np.abs(grasps.xy_theta[:, 1]) <= 0.06 + 1e-9)
    assert np.all(grasps.object_index == 0)
    np.testing.assert_allclose(grasps.poses[:, :3, 2], np.tile([0.0, 0.0, -1.0], (len(grasps), 1)), atol=1e-12)


def test_explicit_poses_on_the_box():
    box = _box((0.05, 0.12, 0.04))
    top = TABLE_TOP_Z_M + 0.04
    check = check_grasp_poses(
        [_topdown_pose(0.5, 0.0, top - 0.01, 0.0),  # across the 5 cm side
         _topdown_pose(0.5, 0.0, top - 0.01, 90.0),  # across the 12 cm side: fingers in the box
         _topdown_pose(0.5, 0.2, top - 0.01, 0.0)],  # beside the box: nothing between the pads
        _points([box]))
    assert check.valid.tolist() == [True, False, False]
    assert check.collision_free.tolist() == [True, False, True]
    assert check.width[0] == pytest.approx(0.05, abs=0.002)
    assert check.object_index[0] == 0
    assert check.num_points_between[2] == 0 and np.isnan(check.width[2])
    # The contact normals face each other along the closing direction (the patches
    # also hold a few samples of the top face at the edge).
    assert np.sum(check.contact_normals[0] * [[-1, 0, 0], [1, 0, 0]], axis=1) == pytest.approx([1, 1], abs=0.01)


def test_sphere_wider_than_the_stroke_has_no_grasps():
    sphere = _on_table(trimesh.creation.icosphere(subdivisions=3, radius=0.05))
    assert len(find_grasps_in_meshes([sphere], np.random.default_rng(0))) == 0


def test_small_sphere_is_grasped():
    """On a sphere of radius R the surface normal at a contact a distance d from the
    centre line makes the angle asin(d / R) with the closing line, so two pads hold it
    only when d <= R sin(atan mu) (the friction cone): for mu = 0.5, 13.4 mm of a 3 cm
    sphere, and the pads close to a chord of at least 2 R cos(atan mu) = 53.7 mm."""
    R, mu = 0.03, 0.5
    sphere = _on_table(trimesh.creation.icosphere(subdivisions=3, radius=R))
    grasps = find_grasps_in_meshes([sphere], np.random.default_rng(0), mu=mu)
    assert len(grasps) > 0
    d_max = R * mu / np.sqrt(1 + mu * mu)
    assert np.all(grasps.widths >= 2 * R / np.sqrt(1 + mu * mu) - 1e-3)
    assert np.all(grasps.widths <= 2 * R + 1e-3)
    # The contacts (re-measured on a dense sample) lie within d_max of the centre line
    # (2 mm for the random samples of the contact layers).
    dense = sample_scene_points([sphere], np.random.default_rng(1), spacing_m=0.002)
    check = check_grasp_poses(grasps.poses, dense, mu=mu)
    c1, c2 = check.contacts[:, 0], check.contacts[:, 1]
    axis = (c2 - c1) / np.linalg.norm(c2 - c1, axis=1, keepdims=True)
    r = sphere.center_mass - c1
    offset = np.linalg.norm(r - np.sum(r * axis, axis=1, keepdims=True) * axis, axis=1)
    # The re-measurement uses other random samples: ~3% of the hands find no dense
    # sample in a pad's 2 mm contact layer, so their contacts are undefined there.
    measured = np.isfinite(offset)
    assert measured.mean() > 0.95
    assert np.all(offset[measured] <= d_max + 2e-3), offset[measured].max()  # 2 mm: sampling
    # The pad centre is at most d_max plus the pad's half width beside the centre line
    # (the pad can touch the sphere near its edge), with 2 mm for the sampling.
    horizontal = np.hypot(grasps.xy_theta[:, 0] - 0.5, grasps.xy_theta[:, 1])
    assert np.all(horizontal <= d_max + PAD_HALF_WIDTH_M + 0.002), horizontal.max()


def test_fingers_may_not_go_through_the_table():
    # A flat 4 x 10 x 2 cm box: its top is at 22 mm, the fingertips 19 mm below the centre.
    flat = _box((0.04, 0.10, 0.02))
    heights = np.array([0.010, 0.015, 0.020, 0.024, 0.030])
    check = check_grasp_poses([_topdown_pose(0.5, 0.0, z, 0.0) for z in heights], _points([flat]))
    expected = heights - FINGERTIP_Z_M >= TABLE_TOP_Z_M + CLEARANCE
    assert expected.tolist() == [False, False, False, True, True]
    assert check.collision_free.tolist() == expected.tolist()
    # The same pose without the table clearance requirement is collision-free.
    relaxed = check_grasp_poses([_topdown_pose(0.5, 0.0, 0.020, 0.0)], _points([flat]),
                                table_z=-1.0)
    assert relaxed.collision_free.tolist() == [True]


def test_searched_grasps_keep_the_fingertips_above_the_table():
    # 3 cm tall: only the shallowest default depth (pad centre level with the top)
    # keeps the fingertips above the table; the deeper candidates are rejected.
    flat = _box((0.04, 0.10, 0.03))
    grasps = find_grasps_in_meshes([flat], np.random.default_rng(0))
    assert len(grasps) > 0
    tips = grasps.poses[:, 2, 3] - FINGERTIP_Z_M
    assert np.all(tips >= TABLE_TOP_Z_M + CLEARANCE - 1e-9)
    assert np.all(grasps.poses[:, 2, 3] >= TABLE_TOP_Z_M + 0.03 - 0.003)


def test_fingers_collide_with_a_neighbouring_object():
    # A 5 cm box with a tall block 45 mm beside it: the block sits where a finger goes.
    box = _box((0.05, 0.12, 0.04))
    block = _box((0.02, 0.02, 0.08), xy=(0.5 + 0.05, 0.0))
    pose = [_topdown_pose(0.5, 0.0, TABLE_TOP_Z_M + 0.03, 0.0)]
    assert check_grasp_poses(pose, _points([box])).valid.tolist() == [True]
    both = check_grasp_poses(pose, _points([box, block]))
    assert both.collision_free.tolist() == [False]
    # The palm (13 cm wide) also hits a block just beyond the fingers (x in 59 ... 69 mm
    # from the centre; the fingers end at 58.5 mm), if it rises above the palm's
    # underside (25 mm above the centre).
    far = _box((0.01, 0.02, 0.09), xy=(0.5 + 0.064, 0.0))
    assert check_grasp_poses(pose, _points([box, far])).collision_free.tolist() == [False]
    low = _box((0.01, 0.02, 0.04), xy=(0.5 + 0.064, 0.0))
    assert check_grasp_poses(pose, _points([box, low])).collision_free.tolist() == [True]


def test_housing_collides_with_tall_neighbours():
    # A 2 cm cube and a 1 cm post 30 - 40 mm beside it across the closing direction:
    # outside the palm (|y| <= 15 mm) but under the housing (radius 40 mm, its
    # underside 31 mm above the grasp centre).
    cube = _box((0.02, 0.02, 0.02))
    pose = [_topdown_pose(0.5, 0.0, TABLE_TOP_Z_M + 0.022, 0.0)]  # fingertips 5 mm above the table
    assert check_grasp_poses(pose, _points([cube])).valid.tolist() == [True]
    tall = _box((0.01, 0.01, 0.06), xy=(0.5, 0.035))
    short = _box((0.01, 0.01, 0.035), xy=(0.5, 0.035))
    assert check_grasp_poses(pose, _points([cube, tall])).collision_free.tolist() == [False]
    assert check_grasp_poses(pose, _points([cube, short])).collision_free.tolist() == [True]


def test_pads_touching_two_objects_is_not_a_grasp():
    # Two 1 cm thick slabs 3 cm apart: the pads would close on one slab each.
    a = _box((0.01, 0.06, 0.04), xy=(0.48, 0.0))
    b = _box((0.01, 0.06, 0.04), xy=(0.52, 0.0))
    check = check_grasp_poses([_topdown_pose(0.5, 0.0, TABLE_TOP_Z_M + 0.03, 0.0)], _points([a, b]))
    assert check.collision_free.tolist() == [True]
    assert check.object_index.tolist() == [-1]
    assert check.valid.tolist() == [False]


def test_wedge_needs_friction():
    # A prism whose sides lean 40 degrees from vertical: their normals make 40 degrees
    # with a horizontal closing line, outside atan(0.5) = 26.6 but inside atan(1) = 45.
    half_top, height = 0.01, 0.03
    half_bottom = half_top + height * np.tan(np.deg2rad(40.0))
    xz = [(-half_bottom, 0.0), (half_bottom, 0.0), (half_top, height), (-half_top, height)]
    vertices = [(x, y, z) for x, z in xz for y in (-0.1, 0.1)]
    wedge = _on_table(trimesh.Trimesh(vertices=vertices).convex_hull)
    assert len(find_grasps_in_meshes([wedge], np.random.default_rng(0), mu=0.5)) == 0
    assert len(find_grasps_in_meshes([wedge], np.random.default_rng(0), mu=1.0)) > 0


def test_found_grasps_pass_the_explicit_check():
    box = _box((0.05, 0.12, 0.04))
    grasps = find_grasps_in_meshes([box], np.random.default_rng(3))
    check = check_grasp_poses(grasps.poses, _points([box], seed=7))
    # Other samples of the same surface: all but borderline cases agree.
    assert check.valid.mean() >= 0.9
    np.testing.assert_allclose(check.width[check.valid], grasps.widths[check.valid], atol=0.004)


def test_tilted_approaches():
    box = _box((0.05, 0.12, 0.04))
    grasps = find_grasps_in_meshes([box], np.random.default_rng(0), approach_max_tilt_deg=15.0)
    assert len(grasps) > 0
    down = -grasps.poses[:, 2, 2]
    assert np.all(down >= np.cos(np.deg2rad(15.0)) - 1e-9)
    assert np.any(down < np.cos(np.deg2rad(1.0)))
    R = grasps.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_candidates():
    # A lying cylinder: curved sides give the first rotation a direction.
    cylinder = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=48)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    cylinder = _on_table(cylinder)
    c = sample_grasp_candidates([cylinder], np.random.default_rng(0), num_samples=60,
                                num_rotations=4, depths=(0.0, 0.01))
    assert len(c) == 60 * 4 * 2
    assert c.angles.shape == (60, 4)
    np.testing.assert_allclose(np.diff(c.angles, axis=1), np.pi / 4)
    np.testing.assert_allclose(c.approach, np.tile([0.0, 0.0, -1.0], (60, 1)))
    # Only surfaces seen from above are sampled.
    assert np.all(c.normals[:, 2] > 0)
    assert np.all(c.origins[:, 2] > TABLE_TOP_Z_M + 0.03 - 1e-9)
    # Where the normal leans sideways, rotation 0 closes along its horizontal part.
    horizontal = c.normals[:, :2] / np.linalg.norm(c.normals[:, :2], axis=1, keepdims=True)
    leaning = np.linalg.norm(c.normals[:, :2], axis=1) > 0.3
    assert leaning.sum() > 10
    x0 = np.cos(c.angles[:, 0, None]) * c.basis_x + np.sin(c.angles[:, 0, None]) * np.cross(c.approach, c.basis_x)
    np.testing.assert_allclose(np.abs(np.sum(x0[leaning, :2] * horizontal[leaning], axis=1)), 1.0, atol=1e-9)


def test_deterministic_for_a_seed():
    meshes = [_box((0.05, 0.12, 0.04)), _on_table(trimesh.creation.icosphere(2, 0.03), xy=(0.6, 0.1))]
    a = find_grasps_in_meshes(meshes, np.random.default_rng(42)).to_dict()
    b = find_grasps_in_meshes(meshes, np.random.default_rng(42)).to_dict()
    c = find_grasps_in_meshes(meshes, np.random.default_rng(43)).to_dict()
    for key in GraspSet.KEYS:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["xy_theta"], c["xy_theta"])
    assert set(np.unique(a["object_index"])) == {0, 1}


def test_grasp_set_round_trip():
    grasps = find_grasps_in_meshes([_box((0.05, 0.12, 0.04))], np.random.default_rng(0))
    data = grasps.to_dict()
    assert set(data) == set(GraspSet.KEYS)
    back = GraspSet.from_dict(data)
    for key in GraspSet.KEYS:
        np.testing.assert_array_equal(getattr(back, key), data[key])
    empty = GraspSet.from_dict(GraspSet.empty().to_dict())
    assert len(empty) == 0 and empty.poses.shape == (0, 4, 4)
    with pytest.raises(ValueError, match="missing keys.*widths"):
        GraspSet.from_dict({k: v for k, v in data.items() if k != "widths"})
    with pytest.raises(ValueError, match="xy_theta"):
        GraspSet(data["poses"], data["widths"], data["xy_theta"][:, :2], data["object_index"])


def test_no_objects_no_grasps():
    grasps = find_grasps_in_meshes([], np.random.default_rng(0))
    assert len(grasps) == 0
    assert distance_to_nearest_grasp(np.zeros((3, 3)), grasps.xy_theta).tolist() == [np.inf] * 3


def test_bad_arguments_are_named():
    box = [_box((0.05, 0.12, 0.04))]
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="rng"):
        find_grasps_in_meshes(box, 0)
    with pytest.raises(ValueError, match="num_samples"):
        find_grasps_in_meshes(box, rng, num_samples=0)
    with pytest.raises(ValueError, match="depths"):
        find_grasps_in_meshes(box, rng, depths=[])
    with pytest.raises(ValueError, match="approach_max_tilt_deg"):
        find_grasps_in_meshes(box, rng, approach_max_tilt_deg=95.0)
    with pytest.raises(ValueError, match="mu"):
        find_grasps_in_meshes(box, rng, mu=-0.1)
    with pytest.raises(ValueError, match=r"meshes\[0\]"):
        find_grasps_in_meshes(["not a mesh"], rng)
    with pytest.raises(ValueError, match="poses"):
        check_grasp_poses(np.zeros((2, 3, 3)), _points(box))
    with pytest.raises(ValueError, match="n2"):
        force_closure(np.zeros(3), np.ones(3), np.ones(3), np.ones(2))


# ----------------------------------------------------------------------------
# Force closure.


def test_force_closure_of_contact_pairs():
    p1, p2 = np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0])
    # Antipodal: normals along the line between the contacts.
    assert force_closure(p1, [-1, 0, 0], p2, [1, 0, 0], mu=0.5)
    assert force_closure(p1, [-1, 0, 0], p2, [1, 0, 0], mu=0.0)
    # Wedge: normals 40 degrees off the line, atan(0.5) = 26.6 < 40 < 45 = atan(1).
    a = np.deg2rad(40.0)
    n1, n2 = [-np.cos(a), 0, np.sin(a)], [np.cos(a), 0, np.sin(a)]
    assert not force_closure(p1, n1, p2, n2, mu=0.5)
    assert force_closure(p1, n1, p2, n2, mu=1.0)
    # Normals pointing away from each other (pinching from inside), and unnormalised.
    assert not force_closure(p1, [1, 0, 0], p2, [-1, 0, 0], mu=1.0)
    assert force_closure(p1, [-3, 0, 0], p2, [0.2, 0, 0.01], mu=0.5)
    # Vectorised over pairs; coincident contacts are no grasp.
    P1 = np.stack([p1, p1, p1])
    N1 = np.array([[-1, 0, 0], n1, [-1, 0, 0]])
    P2 = np.stack([p2, p2, p1])
    N2 = np.array([[1, 0, 0], n2, [1, 0, 0]])
    assert force_closure(P1, N1, P2, N2, mu=0.5).tolist() == [True, False, False]
    # Exactly on the cone's edge counts as inside.
    edge = np.arctan(0.5)
    assert force_closure(p1, [-np.cos(edge), 0, np.sin(edge)], p2, [1, 0, 0], mu=0.5)


# ----------------------------------------------------------------------------
# The distance label.


def test_grasp_distance_weights_and_wraps_the_angle():
    assert grasp_distance([0, 0, 0], [0.003, 0.004, 0]) == pytest.approx(0.005)
    assert grasp_distance([0, 0, 10], [0, 0, 0]) == pytest.approx(0.010)  # 0.001 m/deg
    assert grasp_distance([0.003, 0, 0], [0, 0, 4]) == pytest.approx(0.005)
    assert grasp_distance([0, 0, 1], [0, 0, 179]) == pytest.approx(0.002)  # 180-degree symmetry
    assert grasp_distance([0, 0, 359], [0, 0, 1]) == pytest.approx(0.002)
    assert grasp_distance([0, 0, 0], [0, 0, 90]) == pytest.approx(0.090)  # the largest angle term
    assert grasp_distance([0, 0, 0], [0, 0, 270]) == pytest.approx(0.090)
    assert grasp_distance([0, 0, 0], [0, 0, 10], angle_weight_m_per_deg=0.002) == pytest.approx(0.020)
    rng = np.random.default_rng(0)
    a = rng.uniform([-0.1, -0.1, -360], [0.1, 0.1, 360], size=(50, 3))
    b = rng.uniform([-0.1, -0.1, -360], [0.1, 0.1, 360], size=(50, 3))
    np.testing.assert_allclose(grasp_distance(a, b), grasp_distance(b, a))
    assert np.all(grasp_distance(a, a) == 0.0)
    np.testing.assert_allclose(angle_difference_deg(a[:, 2], b[:, 2] + 180.0), angle_difference_deg(a[:, 2], b[:, 2]),
                               atol=1e-9)


def test_distance_to_nearest_grasp():
    grasps = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 90.0], [0.0, 0.1, 179.0]])
    poses = np.array([
        [0.0, 0.0, 0.0],  # on a grasp
        [0.1, 0.003, 94.0],  # 3 mm and 4 degrees from grasp 1
        [0.0, 0.1, 1.0],  # 2 degrees across the wrap from grasp 2
        [0.05, 0.0, 45.0],  # equidistant-ish: nearest by the weighted metric
    ])
    d = distance_to_nearest_grasp(poses, grasps)
    expected = np.min(grasp_distance(poses[:, None, :], grasps[None, :, :]), axis=1)
    np.testing.assert_allclose(d, expected)
    np.testing.assert_allclose(d[:3], [0.0, 0.005, 0.002], atol=1e-12)
    # Chunking gives the same answer.
    rng = np.random.default_rng(1)
    many_g = rng.uniform([0, 0, 0], [0.2, 0.2, 180], size=(300, 3))
    many_p = rng.uniform([0, 0, 0], [0.2, 0.2, 180], size=(500, 3))
    np.testing.assert_allclose(distance_to_nearest_grasp(many_p, many_g, chunk_elements=1000),
                               distance_to_nearest_grasp(many_p, many_g))
    assert distance_to_nearest_grasp(np.zeros((0, 3)), grasps).shape == (0,)
    with pytest.raises(ValueError, match="poses_xy_theta"):
        distance_to_nearest_grasp(np.zeros((4, 2)), grasps)
    with pytest.raises(ValueError, match="grasps_xy_theta"):
        distance_to_nearest_grasp(poses, np.zeros(3))


# ----------------------------------------------------------------------------
# A built-in object in a real scene.


def test_lying_can_in_a_settled_scene(library):
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{scene: {object_ids: [can_000], pose: lying}}")
    spec = make_scene(scenario.scene, 0, library)
    assert spec.object_ids() == ["can_000"]
    (mesh,) = scene_meshes(spec, library)
    # The numpy pose conversion matches Drake's.
    X = spec.objects[0].pose()
    local = trimesh.load(str(library.get("can_000").directory / "visual.obj"), force="mesh", process=False)
    np.testing.assert_allclose(mesh.vertices, local.vertices @ X.rotation().matrix().T + X.translation(),
                               atol=1e-12)

    grasps = find_grasps(spec, library, np.random.default_rng(0))
    assert len(grasps) > 10
    assert np.all(grasps.object_index == 0)
    lo, hi = mesh.bounds
    assert np.all((grasps.xy_theta[:, :2] >= lo[:2]) & (grasps.xy_theta[:, :2] <= hi[:2]))
    # Across the can (65 mm), never along its 128 mm axis.
    axis = X.rotation().matrix()[:, 2]  # the can's symmetry axis (model z)
    assert abs(axis[2]) < 0.1  # lying
    closing = grasps.poses[:, :3, 0]
    assert np.all(np.abs(closing @ axis) < np.sin(np.deg2rad(30.0)))
    # 65 mm across, up to 65 / cos(26.6 deg) = 73 mm where the closing line is oblique.
    assert np.all((grasps.widths > 0.05) & (grasps.widths < 0.074))


def test_explicit_side_approach():
    # Approaching horizontally along +y into the box's 5 cm wide end, closing along x.
    box = _box((0.05, 0.12, 0.04))
    mid = TABLE_TOP_Z_M + 0.02

    def side_pose(y, x_axis):
        X = np.eye(4)
        z_axis = np.array([0.0, 1.0, 0.0])
        X[:3, :3] = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        X[:3, 3] = [0.5, y, mid]
        return X

    check = check_grasp_poses(
        [side_pose(-0.05, [1.0, 0, 0]),  # pad centres 1 cm in from the end: fine
         side_pose(0.0, [1.0, 0, 0]),  # 6 cm in: the palm (25 mm behind the centre) hits the end
         side_pose(-0.05, [0, 0, 1.0])],  # closing vertically: the lower finger is in the table
        _points([box]))
    assert check.collision_free.tolist() == [True, False, False]
    assert check.valid.tolist() == [True, False, False]
    assert check.width[0] == pytest.approx(0.05, abs=0.003)
    with pytest.raises(ValueError, match="right-handed"):
        check_grasp_poses([np.diag([1.0, 1.0, -1.0, 1.0])], _points([box]))
