"""Keyframe selection: the registered views a template keeps for pose estimation, spread over the
directions the object was seen from, each holding enough keypoints on the object to be matched.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from gscan.settings import SETTINGS


@dataclass(frozen=True)
class KeyframeParams:
    """Which registered views a template keeps as keyframes (`select_keyframes`)."""

    __pydantic_config__ = SETTINGS

    min_angle_deg: Annotated[float, Field(ge=0, description="a new keyframe views the object at least this far from "
                                          "all others")] = 12.0
    max_views: Annotated[int, Field(ge=1, description="at most this many template views")] = 120
    min_views: Annotated[int, Field(ge=1, description="at least this many template views when the capture has them "
                                    "(the angle shrinks for a short sweep)")] = 8
    min_object_keypoints: Annotated[int, Field(ge=0, description="keyframes are views with at least this many "
                                               "keypoints on the object, and views with fewer where none of those "
                                               "looks from")] = 24
    object_keypoints: Annotated[Literal["auto", "sift", "both"], Field(
        description="the keypoints keyframes keep on the object for estimation: the image's (sift), the image's and "
        "the depth's in one set (both; needs features.kind rootsift), or auto: both where the capture registered "
        "with depth keypoints (features.keypoints depth or both) or the keyframes hold a median below "
        "features.auto_min_keypoints image keypoints on the object (a plain object on a printed table), else the "
        "image's")] = "auto"


def view_direction(T_obj_cam: np.ndarray) -> np.ndarray:
    """[3] unit direction from the camera centre to the object frame's origin (the object's centre), in the
    object frame: what the camera sees of the object, also for a sideways sweep that keeps its optical axis."""
    c = np.asarray(T_obj_cam, dtype=np.float64)[:3, 3]
    n = np.linalg.norm(c)
    return -c / n if n > 0 else np.asarray(T_obj_cam, dtype=np.float64)[:3, 2]


def _greedy(order: list[int], dirs: dict[int, np.ndarray], angle: float) -> list[int]:
    chosen: list[int] = []
    for i in order:
        if all(np.degrees(np.arccos(np.clip(float(dirs[i] @ dirs[j]), -1, 1))) >= angle for j in chosen):
            chosen.append(i)
    return chosen


def select_keyframes(view_dirs: dict[int, np.ndarray], min_angle_deg: float, max_views: int,
                     object_keypoints: dict[int, int] | None = None, min_keypoints: int = 0,
                     min_views: int = 1) -> list[int]:
    """Keyframes that cover the object: greedy, best-supplied views first.

    view_dirs: frame index -> unit viewing direction in the object frame (`view_direction`);
    object_keypoints: frame index -> keypoints with depth on the object (None: all equal).
    Frames with at least `min_keypoints` object keypoints are candidates (all frames when fewer than
    `min_views` have that many), taken in order of decreasing count (then index): a frame becomes a keyframe when
    its direction is at least the angle from every keyframe already chosen. The angle starts at `min_angle_deg`; it
    grows by 10 % while more than `max_views` qualify and shrinks by 20 % (down to 0.5 deg) while fewer than
    `min_views` do, so a short sweep over a few degrees still keeps several views. Then a frame with fewer
    keypoints whose direction lies at least that angle from every candidate is added the same way (after the
    others, up to `max_views`): a side of the object that only poorly supplied views saw (a face printed
    plainly, a second capture's other side) keeps a keyframe instead of leaving its directions to views of other
    faces, and the well-supplied keyframes are those chosen without it. Returns sorted indices.
    """
    if not view_dirs:
        return []
    counts = object_keypoints or {}
    order = sorted(view_dirs, key=lambda i: (-counts.get(i, 0), i))
    rich = [i for i in order if counts.get(i, 0) >= min_keypoints]
    rich = rich if len(rich) >= min(min_views, len(order)) else order
    angle = min_angle_deg
    chosen = _greedy(rich, view_dirs, angle)
    while len(chosen) > max_views and angle < 180:
        angle = max(angle * 1.1, angle + 0.5)
        chosen = _greedy(rich, view_dirs, angle)
    while len(chosen) < min(min_views, max_views, len(order)) and angle > 0.5:
        angle = max(angle * 0.8, 0.5)
        chosen = _greedy(rich, view_dirs, angle)
    R = np.array([view_dirs[i] for i in rich])
    rich_set, cos_max = set(rich), np.cos(np.radians(angle))
    poor = [i for i in order if i not in rich_set and float(np.max(R @ view_dirs[i])) <= cos_max]
    chosen = _greedy(chosen + poor, view_dirs, angle)
    return sorted(chosen[:max_views])


def keyframe_candidates(T_obj_cam: list[np.ndarray | None], shows: Callable[[int], bool]) -> dict[int, np.ndarray]:
    """Frame index -> viewing direction (`view_direction`) of the registered frames that show the object
    (`shows(k)`: its object mask is not empty): a frame without it (a sweep that starts elsewhere) would give
    the template its background as the object's keypoints. All registered frames when none shows it."""
    reg = {k: T for k, T in enumerate(T_obj_cam) if T is not None}
    showing = {k: T for k, T in reg.items() if shows(k)}
    return {k: view_direction(T) for k, T in (showing or reg).items()}
