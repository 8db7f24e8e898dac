"""The scan's camera check: a folder capture's colour focal length checked against its data
(`gscan.scanning.calibration`) before the scan, and the capture read again with the one the data give."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from gscan.errors import InputError
from gscan.features import Detection
from gscan.io import open_sequence
from gscan.io.camera import DepthCamera, RGBDFrame
from gscan.io.sequence import Sequence
from gscan.scanning.calibration import check_colour_focal
from gscan.scanning.capture_mode import STATIC_OBJECT
from gscan.scanning.config import for_capture
from gscan.scanning.frames import WORKERS
from gscan.scanning.options import ScanOptions

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence

log = logging.getLogger(__name__)


def check_camera(source: Path, seq: Sequence | RecordingSequence, opts: ScanOptions, detections: dict[str, Detection]
                  ) -> tuple[Sequence | RecordingSequence, dict | None]:
    """A folder capture read with one set of intrinsics (no --depth-intrinsics, one K for every frame): the
    colour camera's focal length checked against the data (gscan.scanning.calibration). When the texture rejects
    the given one, the capture is read again with the given intrinsics as the depth camera's and the focal
    length the data give as the colour camera's. Returns (the sequence to scan, the check's report or None);
    the frames the check detected keypoints in are left in `detections` for the features stage."""
    cfg = opts.config
    if (not cfg.camera.check_colour_focal or opts.depth_camera is not None or not isinstance(seq, Sequence)
            or seq.depth_camera is not None or any(seq.frame_intrinsics(n) != seq.intrinsics for n in seq.names)):
        return seq, None

    def read(i: int) -> RGBDFrame | None:
        try:
            return seq[seq.names[i]]
        except InputError:
            return None

    static = for_capture(cfg, STATIC_OBJECT)
    check = check_colour_focal(read, len(seq.names), static.registration, static.features, cfg.camera,
                               workers=WORKERS, detections=detections)
    if check is None:
        return seq, None
    K = seq.intrinsics
    Kc = check.colour_intrinsics(K)
    # (the intrinsics themselves: `gscan.estimate` reads frames of this camera the same way)
    report = {"given_focal_px": [K.fx, K.fy], "colour_focal_px": [round(Kc.fx, 1), round(Kc.fy, 1)],
              "corrected": check.significant, "pairs": check.pairs,
              "texture_agreement": {"given": round(check.agreement[1.0], 3),
                                    "used": round(check.peak, 3)},
              "given_intrinsics": K.to_dict(), "colour_intrinsics": Kc.to_dict()}
    if not check.significant:
        return seq, report
    log.warning("the depth does not line up with the colour under the given intrinsics: the texture of %d frame "
                "pairs lines up best with a colour focal length of %.1f px (%.0f %% of textured tiles, %.0f %% at the "
                "given %.1f px); scanning with it, the given intrinsics taken as the depth camera's", check.pairs,
                Kc.fx, 100 * check.peak, 100 * check.agreement[1.0], K.fx)
    seq = open_sequence(source, format=opts.format, intrinsics=Kc, depth_scale=opts.depth_scale,
                        obj_id=opts.obj_id, depth_camera=DepthCamera(K))
    return seq, report
