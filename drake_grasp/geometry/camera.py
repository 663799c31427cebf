"""The pinhole camera model every caller uses: intrinsics, projection, back-projection.

Drake's `CameraInfo(width, height, fov_y)` renders square pixels with the focal length
f = (H / 2) / tan(fov_y / 2) and the principal point at the image centre,
(cu, cv) = (W / 2 - 0.5, H / 2 - 0.5) (column, row). Depth is along the optical axis, so
the camera-frame point (x, y, z) (x right, y down, z forward) is seen at pixel

    u = x f / z + cu,    v = y f / z + cv,

and pixel (u, v) with depth z is the point z ((u - cu) / f, (v - cv) / f, 1). On the
wrist, the camera's axes are the hand frame's (the camera looks along the hand's
approach), so the same formulas map a hand-frame offset from the camera at a depth
below it to a pixel and back.

The square footprint the view covers on the table, z tan(fov / 2) either side of the
axis at a camera height z, is `view_half_extent_m`.

Pure numpy; every formula is written once here, in one order of floating-point
operations, so that every caller gets the same bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one image size and field of view.

    Attributes:
        width, height: Image size [pixels].
        focal_px: Focal length [pixels] (square pixels).
        cu, cv: Principal point (column, row) [pixels].
    """

    width: int
    height: int
    focal_px: float
    cu: float
    cv: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_y_deg: float) -> "PinholeCamera":
        """The camera of Drake's `CameraInfo(width, height, fov_y)`.

        Raises:
            ValueError: a size that is not a positive integer, or a field of view that is
                not a finite number in (0, 180) degrees.
        """
        for name, n in (("width", width), ("height", height)):
            if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
                raise ValueError(f"camera {name}: expected a positive integer [pixels], "
                                 f"got {n!r}")
        try:
            fov = float(fov_y_deg)
        except (TypeError, ValueError):
            raise ValueError(f"fov_y_deg: expected a finite number, got {fov_y_deg!r}") from None
        if not (np.isfinite(fov) and 0.0 < fov < 180.0):
            raise ValueError(f"fov_y_deg: expected a finite number > 0.0 and < 180.0, "
                             f"got {fov_y_deg!r}")
        return cls(int(width), int(height), focal_length_px(int(height), fov),
                   width / 2.0 - 0.5, height / 2.0 - 0.5)

    @classmethod
    def centred(cls, width: int, height: int, focal_px: float) -> "PinholeCamera":
        """The camera of this image size and focal length [pixels], principal point at
        the image centre (Drake's convention)."""
        return cls(int(width), int(height), focal_px, width / 2.0 - 0.5, height / 2.0 - 0.5)

    @classmethod
    def of_image(cls, image: np.ndarray, fov_y_deg: float) -> "PinholeCamera":
        """The camera that rendered `image` ((H, W) or (H, W, C)) with this field of view."""
        h, w = np.shape(image)[:2]
        return cls.from_fov(int(w), int(h), fov_y_deg)

    def project(self, x, y, z):
        """Pixel (u, v) of camera-frame coordinates (x, y) at depth z (arrays broadcast)."""
        return (x * self.focal_px / z + self.cu, y * self.focal_px / z + self.cv)

    def back_project(self, u, v, z):
        """Camera-frame (x, y) of pixel (u, v) at depth z (arrays broadcast)."""
        return ((u - self.cu) * z / self.focal_px, (v - self.cv) * z / self.focal_px)

    def metres_to_pixels(self, length_m, z):
        """How many pixels a length [m] across the view spans at depth z."""
        return length_m * self.focal_px / z

    def pixels_to_metres(self, z):
        """The side [m] of one pixel's footprint at depth z."""
        return z / self.focal_px


def focal_length_px(height: int, fov_y_deg: float) -> float:
    """Focal length [pixels] of an image `height` pixels tall with this vertical field of
    view [deg]: (H / 2) / tan(fov_y / 2)."""
    return float(0.5 * height / np.tan(np.deg2rad(fov_y_deg) / 2.0))


def view_half_extent_m(camera_height_m, fov_deg: float) -> np.ndarray:
    """Half width of the square camera footprint on the table at a given camera height."""
    return np.asarray(camera_height_m, dtype=float) * np.tan(np.deg2rad(fov_deg) / 2.0)
