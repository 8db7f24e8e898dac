"""The scan's camera check: a folder capture's colour focal length checked against its data
(`gscan.scanning.calibration`) before the scan, and the capture read again with the one the data give."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gscan.errors import InputError
from gscan.features import Detection
from gscan.io import open_sequence
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame
from gscan.io.sequence import Sequence, spread_indices
from gscan.scanning.calibration import KEPT, SCALES, UNCONFIRMED, FocalCheck, check_colour_focal
from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.config import for_capture
from gscan.scanning.depth_edges import EdgeEvidence, edge_evidence
from gscan.scanning.frames import WORKERS
from gscan.scanning.options import ScanOptions

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence

log = logging.getLogger(__name__)

# the texture check registers the camera's motion over whole frames: before a static camera the background lines up
# at any focal length (printed objects on a turntable: 93-98 % of the tiles at every scale tried), and a plain
# object's few keypoints and rim shading peak anywhere (a rendered plain box at 615 px "corrected" to 668 px)
MOVED_NOT = ("the camera did not move (a moving object before a static camera): the texture check needs the camera's "
             "own motion over a still scene")


def check_camera(source: Path, seq: Sequence | RecordingSequence, opts: ScanOptions, detections: dict[str, Detection],
                 mode: str = STATIC_OBJECT) -> tuple[Sequence | RecordingSequence, dict | None]:
    """A folder capture read with one set of intrinsics (no --depth-intrinsics, one K for every frame): the
    colour camera's focal length checked against the data (gscan.scanning.calibration). When the texture rejects
    the given one, the capture is read again with the given intrinsics as the depth camera's and the focal
    length the data give as the colour camera's. Returns (the sequence to scan, the check's report or None);
    the frames the check detected keypoints in are left in `detections` for the features stage. The report
    (`camera_report`) also holds the depth-edge evidence (`gscan.scanning.depth_edges`) of `edge_frames` frames
    spread over the capture; a check that could not confirm the focal length is logged as a warning and the
    capture scanned with the given intrinsics. mode: the capture's (`gscan.scanning.capture_mode`); before a
    static camera (MOVING_OBJECT) the texture check cannot tell (`MOVED_NOT`) and is not run."""
    cfg = opts.config
    if (not cfg.camera.check_colour_focal or opts.depth_camera is not None or not isinstance(seq, Sequence)
            or seq.depth_camera is not None or any(seq.frame_intrinsics(n) != seq.intrinsics for n in seq.names)):
        return seq, None

    def read(i: int) -> RGBDFrame | None:
        try:
            return seq[seq.names[i]]
        except InputError:
            return None

    if mode == MOVING_OBJECT:
        check = FocalCheck.not_confirmed(MOVED_NOT)
    else:
        static = for_capture(cfg, STATIC_OBJECT)
        check = check_colour_focal(read, len(seq.names), static.registration, static.features, cfg.camera,
                                   workers=WORKERS, detections=detections)
    spread = spread_indices(len(seq.names), cfg.camera.edge_frames)
    edges = edge_evidence([f for f in (read(i) for i in spread) if f is not None], SCALES)
    K = seq.intrinsics
    report = camera_report(check, edges, K, list(seq.names))
    if not report["confirmed"]:  # said by the scan's summary and --json (a warning here would precede a bad input's
        log.info("colour camera: %s", report["warning"])  # one error line)
    if not check.significant:
        return seq, report
    Kc = check.colour_intrinsics(K)
    log.warning("the depth does not line up with the colour under the given intrinsics: the texture of %d frame "
                "pairs lines up best with a colour focal length of %.1f px (%.1f-%.1f px; %.0f %% of textured tiles, "
                "%.0f %% at the given %.1f px); scanning with it, the given intrinsics taken as the depth camera's",
                check.pairs, Kc.fx, K.fx * check.low, K.fx * check.high, 100 * check.peak,
                100 * check.agreement[1.0], K.fx)
    seq = open_sequence(source, format=opts.format, intrinsics=Kc, depth_scale=opts.depth_scale,
                        obj_id=opts.obj_id, depth_camera=DepthCamera(K))
    return seq, report


FLAGS = "--intrinsics (the colour camera's), --depth-intrinsics and --depth-to-color (the depth camera's)"


def camera_report(check: FocalCheck, edges: EdgeEvidence, K: Intrinsics, frames: list[str]) -> dict:
    """The check's report (`scan --json`'s "camera", the template's "camera" meta): the focal length given and
    used (px), the estimate and its interval (px; null where unbounded), the verdict, confirmed (kept or corrected),
    the reason and the warning when not, the texture's agreement, the depth-edge evidence, and the frames whose
    poses rest on a focal length the check could not confirm (every frame of the capture; none when confirmed).
    Depth edges off the colour edges turn a texture check that would keep the given intrinsics into one that could
    not confirm them: the texture cannot tell a colour camera of the given focal length from a depth that is not
    registered to it when both line up about as well."""
    Kc = check.colour_intrinsics(K)
    verdict, reason = check.verdict, check.reason
    e = edges.to_dict()
    off = edges.verdict == "not registered"
    if off:
        e["fix"] = (f"the depth's jumps lie {edges.offset_px:.0f} px (median) off the colour edges at the given "
                    f"calibration (best at x{edges.scale:.2f} the focal length): the depth is not registered to the "
                    f"colour; pass {FLAGS}")
    if verdict == KEPT and off:
        verdict, reason = UNCONFIRMED, e["fix"]

    def px(x: float) -> float | None:
        return round(K.fx * x, 1) if np.isfinite(x) else None

    def num(x: float) -> float | None:
        return round(x, 3) if np.isfinite(x) else None

    confirmed = verdict != UNCONFIRMED
    warning = None
    if not confirmed:
        best = (f"; the texture lines up best at {px(check.estimate)} px (interval {px(check.low) or '?'}-"
                f"{px(check.high) or '?'} px)" if np.isfinite(check.estimate) else "")
        warning = (f"could not confirm the focal length {K.fx:g} px ({reason}){best}; scanned with the given "
                   f"{K.fx:g} px: the poses of all {len(frames)} frames rest on it"
                   + ("" if off else f"; a known calibration: {FLAGS}"))
    return {"given_focal_px": [K.fx, K.fy], "colour_focal_px": [round(Kc.fx, 1), round(Kc.fy, 1)],
            "verdict": verdict, "confirmed": confirmed, "corrected": check.significant, "reason": reason,
            "warning": warning, "estimate_px": px(check.estimate), "interval_px": [px(check.low), px(check.high)],
            "pairs": check.pairs, "p_value": round(check.p_value, 4),
            "texture_agreement": {"given": num(check.agreement.get(1.0, float("nan"))), "used": num(check.peak)},
            "depth_edges": e, "unconfirmed_frames": [] if confirmed else frames,
            "given_intrinsics": K.to_dict(), "colour_intrinsics": Kc.to_dict()}
