"""Gray values of the feature in a captured image: at the projected feature samples, and over
the feature's image region (the convex hull of the projected samples)."""
import cv2
import numpy as np

from cell import projection


def sample_pixels(task, T_cell_cam, points):
    """Nearest pixel (row, col) of each feature sample seen from the actual camera pose, and
    whether it falls inside the image."""
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    uv, _ = projection.project(K, T_cell_cam, points)
    sensor = task.camera.sensor
    col = np.rint(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(int)
    row = np.rint(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(int)
    inside = (col >= 0) & (col < sensor.width_px) & (row >= 0) & (row < sensor.height_px)
    return row, col, inside


def feature_mask(shape, row, col):
    """Pixels inside the convex hull of the samples' pixels (the feature's image region)."""
    mask = np.zeros(shape, dtype=np.uint8)
    if len(row):
        hull = cv2.convexHull(np.column_stack([col, row]).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def saturation_level(bit_depth):
    """The largest gray a bit_depth sensor reports: a pixel there may truly be brighter."""
    return 2 ** int(bit_depth) - 1
