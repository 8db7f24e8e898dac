"""`ScanOptions`: every option of one scan (`gscan scan`, `gscan.scan`), one typed value passed from the command
line through the API to the pipeline. The stages' settings are its `config` (`ScanConfig`)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gscan.io.camera import DepthCamera
from gscan.io.layouts import FORMATS
from gscan.scanning.modes import MOVING_OBJECT, STATIC_OBJECT

if TYPE_CHECKING:
    from gscan.scanning.config import ScanConfig

#: the input layouts `format` may name ("auto": detected)
FORMAT_CHOICES = ("auto", *FORMATS)
#: the capture modes `mode` may name ("auto": detected from a few frames)
MODE_CHOICES = ("auto", STATIC_OBJECT, MOVING_OBJECT)


@dataclass(frozen=True)
class ScanOptions:
    """How one scan reads its input and writes its output (the source and the output are given beside it).

    format: the input layout, one of FORMAT_CHOICES; intrinsics: a cam_K.txt / Open3D JSON overriding the layout's;
    depth_scale: metres per raw depth unit overriding the layout's; mode: one of MODE_CHOICES; segment: fuse the
    object alone (False: the whole scene); resume: continue an interrupted scan into the output; append: add the
    captures to the existing template at the output (its views, poses and frame kept; left as it was when a capture
    cannot be joined to it); force: replace an
    existing output; config: the stages' settings; obj_id: a BOP folder's object (None: the first in
    scene_gt.json); color_topic, depth_topic: a recording's image topics (None: detected when unambiguous);
    depth_camera: depth images not registered to colour (a Kinect v1): their own camera, its intrinsics and its
    pose in the colour camera (`gscan.io.camera.DepthCamera`, from `load_depth_camera(intrinsics, T_color_depth)`);
    meta: more keys for the template's meta table (JSON values); roi: the object's box (x, y, width, height in
    pixels) in the first frame of the first capture, or mask: a mask image of that frame (non-zero on the object):
    the object segmentation keeps (None: chosen from where the views look; `gscan.scanning.segment`).
    """

    format: str = "auto"
    intrinsics: Path | None = None
    depth_scale: float | None = None
    mode: str = "auto"
    segment: bool = True
    resume: bool = False
    append: bool = False
    force: bool = False
    config: ScanConfig = field(default_factory=lambda: _default_config())
    obj_id: int | None = None
    color_topic: str | None = None
    depth_topic: str | None = None
    depth_camera: DepthCamera | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    roi: tuple[int, int, int, int] | None = None
    mask: Path | None = None

    def __post_init__(self) -> None:
        if self.format not in FORMAT_CHOICES:
            raise ValueError(f"format must be one of {', '.join(FORMAT_CHOICES)}, not {self.format!r}")
        if self.append and (self.resume or self.force):
            raise ValueError("append excludes resume and force")
        if self.mode not in MODE_CHOICES:
            raise ValueError(f"mode must be one of {', '.join(MODE_CHOICES)}, not {self.mode!r}")
        if self.intrinsics is not None and not isinstance(self.intrinsics, Path):
            object.__setattr__(self, "intrinsics", Path(self.intrinsics))
        if self.roi is not None and self.mask is not None:
            raise ValueError("roi and mask exclude each other")
        if self.roi is not None:
            if len(self.roi) != 4 or self.roi[2] <= 0 or self.roi[3] <= 0:
                raise ValueError(f"roi must be (x, y, width, height) with a positive width and height, not {self.roi}")
            object.__setattr__(self, "roi", tuple(int(v) for v in self.roi))
        if self.mask is not None and not isinstance(self.mask, Path):
            object.__setattr__(self, "mask", Path(self.mask))
        if self.depth_camera is not None and not isinstance(self.depth_camera, DepthCamera):
            raise TypeError(f"depth_camera must be a DepthCamera (gscan.io.camera.load_depth_camera), not "
                            f"{type(self.depth_camera).__name__}")


def _default_config() -> ScanConfig:
    """The default `ScanConfig`, its module imported when first needed: the stages' settings classes load numba
    and scipy, which the command line's choices (FORMAT_CHOICES, MODE_CHOICES) do without."""
    from gscan.scanning.config import ScanConfig

    return ScanConfig()
