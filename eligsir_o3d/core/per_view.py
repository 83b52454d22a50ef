"""What an update derives from a view (its pose and camera), kept for the views seen recently.

Training revisits the same retained views over and over, so the host scalars and device tensors that a view's
update needs (the view test's bounds, gsplat's camera matrices) are made once per view, not once per update. A
view is keyed by its pose's bytes and its (frozen, hashable) camera; a moved pose is a new view."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable

import numpy as np

from .camera import Camera


class PerView:
    """A bounded cache (``size`` views, least recently used out first) of ``make(camera, T_world_cam, *extra)``."""

    def __init__(self, make: Callable[..., Any], size: int = 1024):
        self.make, self.size = make, int(size)
        self._cache: OrderedDict[tuple, Any] = OrderedDict()

    def __len__(self) -> int:
        return len(self._cache)

    def __call__(self, camera: Camera, T_world_cam, *extra) -> Any:
        T = np.asarray(T_world_cam, dtype=np.float64)
        key = (T.tobytes(), camera, *extra)
        hit = self._cache.get(key)
        if hit is None:
            hit = self._cache[key] = self.make(camera, T, *extra)
            if len(self._cache) > self.size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        return hit
