"""PerView: what an update derives from a view is made once per pose and camera, and the cache stays bounded."""

import numpy as np

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.per_view import PerView

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def test_a_view_is_made_once_and_a_moved_pose_or_other_camera_is_a_new_view():
    made = []
    cache = PerView(lambda cam, T, extra: made.append((cam, T.copy(), extra)) or len(made), size=2)
    T = np.eye(4)
    assert cache(CAM, T, 0.3) == cache(CAM, T.tolist(), 0.3) == 1  # the same pose, however it is given
    moved = T.copy()
    moved[0, 3] = 1e-9
    assert cache(CAM, moved, 0.3) == 2
    assert cache(CAM.scaled(0.5), T, 0.3) == 3 and cache(CAM, T, 0.4) == 4
    assert len(made) == 4 and len(cache) == 2  # the least recently used views went out
    assert cache(CAM, T, 0.3) == 5  # made again once evicted
