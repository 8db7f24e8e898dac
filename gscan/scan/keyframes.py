"""Keyframe selection: the registered views a template keeps for pose estimation, spread over the
viewing directions.
"""
from __future__ import annotations

import numpy as np


def select_keyframes(view_dirs: dict[int, np.ndarray], min_angle_deg: float, max_views: int) -> list[int]:
    """Keyframes that cover the object: greedy in input order.

    view_dirs: frame index -> unit viewing direction in the object frame (camera z axis).
    A frame becomes a keyframe when its direction is at least `min_angle_deg` from every
    keyframe already chosen (the first registered frame always is). When more than `max_views`
    qualify, the angle grows by 10 % until they fit. Returns sorted frame indices.
    """
    order = sorted(view_dirs)
    if not order:
        return []
    angle = min_angle_deg
    while True:
        chosen: list[int] = []
        for i in order:
            d = view_dirs[i]
            if all(np.degrees(np.arccos(np.clip(float(d @ view_dirs[j]), -1, 1))) >= angle for j in chosen):
                chosen.append(i)
        if len(chosen) <= max_views or angle >= 180:
            return chosen
        angle = max(angle * 1.1, angle + 0.5)
