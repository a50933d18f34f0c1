"""Camera geometry, pure torch: the OpenCV camera model, rays, rotations and weighted triangulation.

Everything here broadcasts over leading dimensions, works in float32 and float64 and is differentiable.
Conventions (docs/method.md#conventions): ``x_cam = R @ x_world + t``; pixel (0, 0) is the centre of the
top-left pixel, u right, v down; ``K`` is a general 3x3 (skew allowed, so warps ``K <- M @ K`` stay exact);
``dist = (k1, k2, p1, p2, k3)`` as in OpenCV. Dimension names: ``L`` the leading dims of a camera set (e.g.
``(C,)`` for a rig, ``(B, C)`` per frame), ``N`` points, ``V`` views of one point.

:mod:`s3k.geometry.cameras` holds the camera model, :mod:`s3k.geometry.projection` projection and rays,
:mod:`s3k.geometry.distortion` the lens model, :mod:`s3k.geometry.rotations` Rodrigues conversions,
:mod:`s3k.geometry.triangulation` the solver (:mod:`s3k.geometry.shapes`: their argument checks).
:mod:`s3k.geometry.framing` (numpy, not imported here) frames a 3D view on a rig's work;
:mod:`s3k.geometry.consistency` (not imported here) checks a calibration against 2D labels.
"""

from s3k.geometry.cameras import Cameras, camera_centres
from s3k.geometry.distortion import distort, undistort
from s3k.geometry.projection import pixel_rays, project, undistort_pixels
from s3k.geometry.rotations import matrix_to_rodrigues, rodrigues_to_matrix
from s3k.geometry.triangulation import (
    triangulate_labels,
    triangulate_pixels,
    triangulate_rays,
    workspace_centre,
)

__all__ = [
    "Cameras",
    "camera_centres",
    "distort",
    "matrix_to_rodrigues",
    "pixel_rays",
    "project",
    "rodrigues_to_matrix",
    "triangulate_labels",
    "triangulate_pixels",
    "triangulate_rays",
    "undistort",
    "undistort_pixels",
    "workspace_centre",
]
