"""Recording captures from a RealSense camera (or a RealSense recording played back) into the capture layout.

    run_capture(RealSenseCamera(recording=None | path, CameraOptions(...)), output, CaptureOptions(...),
                stop=threading.Event(), on_frame=callback) -> CaptureResult

Modules: `camera` (pyrealsense2 pipeline, colour + depth aligned to colour, millimetres), `motion` (the
motion cue that keeps frames, and the coverage of viewing directions), `record` (the loop and the writer).
The live preview is `gscan.viewer.capture_preview` (the only part that imports viser).
"""
from __future__ import annotations

from gscan._lazy import lazy_exports

# imported on first use: `gscan capture` checks its folder (`gscan.capture.folder`) before these load
_EXPORTS = {
    **dict.fromkeys(("CameraFrame", "CameraOptions", "RealSenseCamera"), "gscan.capture.camera"),
    **dict.fromkeys(("Coverage", "MotionParams", "MotionTracker"), "gscan.capture.motion"),
    **dict.fromkeys(("CaptureOptions", "CaptureResult", "FrameUpdate", "run_capture"), "gscan.capture.record"),
}

__all__ = ["CameraFrame", "CameraOptions", "CaptureOptions", "CaptureResult", "Coverage", "FrameUpdate",
           "MotionParams", "MotionTracker", "RealSenseCamera", "run_capture"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
