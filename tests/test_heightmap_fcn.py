"""analysis/heightmap_fcn.py: the metric height map puts a box where the grid head's
pixel convention puts it, at its height; the net maps it to the grid's shape; training
writes its model and resumes without repeating an epoch."""

import json
import math

import numpy as np
import pytest
import torch



def _box_image(H, cam_h, centre_xy, half_m, top_h):
    """A flat table at cam_h below the camera and a box of side 2 half_m, top at top_h
    above the table, centred at `centre_xy` (camera-axis offsets, x along the image's
    columns, y along its rows, as `WindowHead.window_grid` maps them)."""
    cfg = H.GRID_CONFIG
    f, size = cfg.focal_px, cfg.image_size
    c = np.arange(size) - (size / 2.0 - 0.5)
    depth = np.full((size, size), cam_h, np.float32)
    top = cam_h - top_h
    x = c[None, :] * top / f
    y = c[:, None] * top / f
    inside = (np.abs(x - centre_xy[0]) <= half_m) & (np.abs(y - centre_xy[1]) <= half_m)
    depth[inside] = top
    return depth


def _labels(H, tmp_path, k, *, seed):
    """A dense-labels folder of k box images at 0.25 m with random grids: (folder, data)."""
    t_bins, n, _ = H.GRID_CONFIG.grid_shape()
    rng = np.random.default_rng(seed)
    data = {"depth": np.stack([_box_image(H, 0.25, rng.uniform(-0.05, 0.05, 2), 0.02, 0.05)
                               for _ in range(k)]).astype(np.float16),
            "grid": rng.uniform(0.0, 0.2, (k, t_bins, n, n)).astype(np.float16),
            "hand_z": np.full(k, 0.25 + H.camera_z_G(), np.float32)}
    labels = tmp_path / "labels"
    labels.mkdir()
    np.savez(labels / "shard-00000.npz", **data)
    return labels, data


def test_height_map_places_a_box_at_its_metric_position_and_height(analysis_script):
    H = analysis_script("heightmap_fcn")
    cam_h, centre, half, top_h = 0.25, (-0.06, 0.04), 0.02, 0.05
    hand_z = cam_h + H.camera_z_G()
    m = H.height_maps(_box_image(H, cam_h, centre, half, top_h)[None], np.array([hand_z]))
    assert m.shape == (1, 2, H.LATTICE, H.LATTICE) and m.dtype == np.float16
    heights = m[0, 0].astype(np.float32) / H.HEIGHT_SCALE
    cells = (np.arange(H.LATTICE) - (H.LATTICE - 1) / 2) * H.CELL_M
    # Every cell inside the box holds its top; the table more than two cells (the
    # filling's reach, which closes the box's occlusion shadow) outside it is at 0.
    dx = np.abs(cells[None, :] - centre[0])
    dy = np.abs(cells[:, None] - centre[1])
    inside = (dx <= half - H.CELL_M / 2) & (dy <= half - H.CELL_M / 2)
    assert inside.sum() >= 49 and np.all(np.abs(heights[inside] - top_h) < 1e-3)
    outside = ((dx > half + 2.5 * H.CELL_M) | (dy > half + 2.5 * H.CELL_M)) & (m[0, 1] > 0)
    assert outside.sum() > 1000 and np.all(heights[outside] == 0)
    # The view mask is the camera's footprint on the table.
    half_view = cam_h * math.tan(math.radians(H.GRID_CONFIG.camera_fov_deg) / 2)
    view_cols = np.nonzero(m[0, 1, H.LATTICE // 2] > 0)[0]
    assert abs(cells[view_cols].max() - half_view) <= H.CELL_M
    assert heights[m[0, 1] == 0].max() == 0


def test_fcn_output_is_the_grid_and_training_resumes(tmp_path, analysis_script):
    H = analysis_script("heightmap_fcn")
    t_bins, n, _ = H.GRID_CONFIG.grid_shape()
    net = H.make_fcn(8, False, dilations=(1, 2))
    out = net(torch.zeros(3, 2, H.LATTICE, H.LATTICE))
    assert out.shape == (3, t_bins, n, n) and bool((out > 0).all())

    k = 8
    labels, data = _labels(H, tmp_path, k, seed=0)
    run = tmp_path / "run"
    H.train([str(labels)], run, minutes=5, epochs=2, batch=4, lr=1e-3, width=8, seed=0,
            threads=1)
    saved = torch.load(run / "model.pt", weights_only=False)
    log = saved["state"]["log"]
    assert [e["epoch"] for e in log] == [1, 2] and saved["state"]["epoch"] == 2
    assert all(math.isfinite(e["train_l1_m"]) for e in log)
    before = json.dumps(log)
    H.train([str(labels)], run, minutes=5, epochs=2, batch=4, lr=1e-3, width=8, seed=0,
            threads=1)  # finished: nothing is trained or logged again
    assert json.dumps(torch.load(run / "model.pt", weights_only=False)["state"]["log"]) == before
    with pytest.raises(ValueError, match=r"another training run \(differs in \['width'\]\)"):
        H.train([str(labels)], run, minutes=5, epochs=2, batch=4, lr=1e-3, width=16, seed=0,
                threads=1)
    result = H.metrics(H.predict_fcn(str(run / "model.pt"), data)[0], data, images=k)
    assert result["nodes"] > 0 and result["dense_l1_mm"] > 0


def test_grasp_map_distances_are_the_metric_to_the_nearest_grasp_node(analysis_script):
    H = analysis_script("heightmap_fcn")
    t_bins, n, _ = H.GRID_CONFIG.grid_shape()
    hand_z = np.array([0.30 + H.camera_z_G(), 0.30 + H.camera_z_G()])  # a wide view
    logits = np.full((2, t_bins, n, n), -10.0, np.float32)
    logits[0, 1, 16, 16] = 3.0            # p = 0.95 at theta bin 1, the centre node
    logits[1, 5, 10, 10] = -0.5           # p = 0.38: under the threshold
    d = H.grasp_map_distances(logits, hand_z, threshold=0.5)
    assert np.isnan(d[1]).all()
    step = H.GRID_CONFIG.grid_step_m
    T, Y, X = np.meshgrid(np.arange(t_bins), np.arange(n), np.arange(n), indexing="ij")
    dt = np.minimum(np.abs(T - 1), t_bins - np.abs(T - 1))  # theta wraps at 180 degrees
    expected = step * np.sqrt(dt**2 + (Y - 16) ** 2 + (X - 16) ** 2)
    assert np.allclose(d[0], expected, atol=1e-6)
    assert d[0, t_bins - 1, 16, 16] == pytest.approx(2 * step)  # -90 deg is 20 deg from -70


def test_grasp_head_trains_and_its_variants_fall_back_to_the_distance_head(tmp_path, analysis_script):
    H = analysis_script("heightmap_fcn")
    t_bins, n, _ = H.GRID_CONFIG.grid_shape()
    net = H.make_fcn(8, True, dilations=(1,))
    dist, logits = net.outputs(torch.zeros(2, 2, H.LATTICE, H.LATTICE))
    assert dist.shape == logits.shape == (2, t_bins, n, n)
    labels, data = _labels(H, tmp_path, 4, seed=1)
    hand_z = data["hand_z"]
    run = tmp_path / "run"
    H.train([str(labels)], run, minutes=5, epochs=1, batch=2, lr=1e-3, width=8, seed=0,
            threads=1, grasp_weight=1.0)
    saved = torch.load(run / "model.pt", weights_only=False)
    assert saved["grasp_head"] and math.isfinite(saved["state"]["log"][0]["train_bce"])
    dist, logits = H.predict_fcn(str(run / "model.pt"), data)
    assert logits is not None and logits.shape == dist.shape
    logits[0] = -20.0  # image 0 has no grasp node: both variants give the distance head
    logits[1, 0, 16, 16] = 20.0
    v = H.grasp_map_variants(dist, logits, hand_z, 0.5)
    assert np.array_equal(v["grasp map"][0], dist[0])
    assert np.array_equal(v["min(grasp map, distance head)"][0], dist[0])
    assert v["grasp map"][1, 0, 16, 16] == 0.0
    assert np.all(v["min(grasp map, distance head)"] <= dist)


def test_grasp_node_oracle_recovers_labels_that_are_a_distance_transform(analysis_script):
    H = analysis_script("heightmap_fcn")
    t_bins, n, _ = H.GRID_CONFIG.grid_shape()
    hand_z = np.full(3, 0.30 + H.camera_z_G(), np.float32)
    logits = np.full((3, t_bins, n, n), -10.0, np.float32)
    logits[0, 3, 12, 20] = logits[1, 9, 16, 16] = logits[1, 9, 5, 25] = 10.0
    grid = H.grasp_map_distances(logits, hand_z, 0.5)
    grid[2] = 0.2  # no grasp node: left out
    data = {"depth": np.zeros((3, 64, 64), np.float16), "grid": grid.astype(np.float16),
            "hand_z": hand_z}
    result = H.grasp_node_oracle(data)
    assert result["images_with_a_grasp_node"] == 2 and result["images"] == 3
    assert result["dense_l1_mm"] < 0.1  # float16 rounding of the labels only


def test_height_maps_of_a_batch_are_those_of_all_images(analysis_script):
    """Training makes the maps per batch: each image's map does not depend on the others
    made with it."""
    H = analysis_script("heightmap_fcn")
    rng = np.random.default_rng(4)
    hand_z = 0.2 + rng.uniform(0.0, 0.15, 40) + H.camera_z_G()
    depth = np.stack([_box_image(H, z - H.camera_z_G(), rng.uniform(-0.05, 0.05, 2), 0.02,
                                 rng.uniform(0.01, 0.08)) for z in hand_z])
    whole = H.height_maps(depth, hand_z)
    idx = np.sort(rng.choice(40, 7, replace=False))
    assert np.array_equal(H.height_maps(depth[idx], hand_z[idx]), whole[idx])


def test_a_run_killed_mid_epoch_resumes_to_the_same_weights(tmp_path, analysis_script, monkeypatch):
    """With checkpoints after every batch (`checkpoint_minutes=0`), a run killed in its
    first epoch's fourth batch resumes at its third checkpoint and ends with the weights
    of a run never stopped."""
    H = analysis_script("heightmap_fcn")
    labels, _ = _labels(H, tmp_path, 12, seed=2)
    kw = dict(minutes=5, epochs=2, batch=2, lr=1e-3, width=8, seed=0, threads=1,
              checkpoint_minutes=0.0)
    H.train([str(labels)], tmp_path / "whole", **kw)

    made = H.height_maps
    calls = {"n": 0}

    def killed_in_batch_4(*args):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt("killed")
        return made(*args)

    monkeypatch.setattr(H, "height_maps", killed_in_batch_4)
    with pytest.raises(KeyboardInterrupt):
        H.train([str(labels)], tmp_path / "killed", **kw)
    assert not (tmp_path / "killed" / "model.pt").exists()
    state = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=False)["state"]
    assert (state["epoch"], state["batch_index"]) == (0, 3)
    monkeypatch.setattr(H, "height_maps", made)
    H.train([str(labels)], tmp_path / "killed", **kw)
    whole = torch.load(tmp_path / "whole" / "model.pt", weights_only=False)
    resumed = torch.load(tmp_path / "killed" / "model.pt", weights_only=False)
    assert resumed["state"]["epoch"] == 2
    for k, v in whole["model"].items():
        assert torch.equal(v, resumed["model"][k]), k
