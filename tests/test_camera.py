"""The one camera model (geometry.camera) against Drake's CameraInfo and itself."""

import numpy as np
import pytest
from pydrake.systems.sensors import CameraInfo

from drake_grasp.geometry.camera import PinholeCamera, focal_length_px


@pytest.mark.parametrize("w,h,fov", [(64, 64, 55.0), (640, 480, 45.0), (33, 17, 90.0)])
def test_intrinsics_are_drakes(w, h, fov):
    cam = PinholeCamera.from_fov(w, h, fov)
    info = CameraInfo(width=w, height=h, fov_y=np.deg2rad(fov))
    assert cam.focal_px == pytest.approx(info.focal_x(), rel=1e-12)
    assert cam.focal_px == pytest.approx(info.focal_y(), rel=1e-12)
    assert (cam.cu, cam.cv) == pytest.approx((info.center_x(), info.center_y()), abs=1e-12)
    assert focal_length_px(h, fov) == cam.focal_px


def test_projection_round_trip():
    cam = PinholeCamera.of_image(np.zeros((48, 64)), 55.0)
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 64, 100), rng.uniform(0, 48, 100)
    z = rng.uniform(0.1, 1.0, 100)
    x, y = cam.back_project(u, v, z)
    uu, vv = cam.project(x, y, z)
    np.testing.assert_allclose(uu, u, atol=1e-9)
    np.testing.assert_allclose(vv, v, atol=1e-9)
    # The principal point looks along the optical axis; one pixel is z / f wide.
    assert cam.back_project(cam.cu, cam.cv, 0.5) == (0.0, 0.0)
    assert cam.pixels_to_metres(0.5) * cam.metres_to_pixels(1.0, 0.5) == pytest.approx(1.0)


def test_points_seen_by_a_drake_render_geometry():
    """A point 0.1 m right of the axis at 0.5 m depth lands where CameraInfo's intrinsic
    matrix puts it."""
    info = CameraInfo(width=64, height=64, fov_y=np.deg2rad(55.0))
    cam = PinholeCamera.from_fov(64, 64, 55.0)
    uvw = info.intrinsic_matrix() @ np.array([0.1, -0.05, 0.5])
    assert cam.project(0.1, -0.05, 0.5) == pytest.approx(tuple(uvw[:2] / uvw[2]), abs=1e-9)


@pytest.mark.parametrize("args,match", [((0, 64, 55.0), "width"), ((64, 2.5, 55.0), "height"),
                                        ((64, 64, 180.0), "fov_y_deg"),
                                        ((64, 64, float("nan")), "fov_y_deg"),
                                        ((64, 64, "wide"), "fov_y_deg")])
def test_bad_camera_is_named(args, match):
    with pytest.raises(ValueError, match=match):
        PinholeCamera.from_fov(*args)
