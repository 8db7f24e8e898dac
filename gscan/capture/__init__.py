"""Recording captures from a RealSense camera (or a RealSense recording played back) into the capture layout.

    run_capture(RealSenseCamera(recording=None | path, CameraOptions(...)), output, CaptureOptions(...),
                stop=threading.Event(), on_frame=callback) -> CaptureResult

Modules: `camera` (pyrealsense2 pipeline, colour + depth aligned to colour, millimetres), `motion` (the
motion cue that keeps frames, and the coverage of viewing directions), `record` (the loop and the writer).
The live preview is `gscan.viewer.capture_preview` (the only part that imports viser).
"""
from gscan.capture.camera import CameraFrame, CameraOptions, RealSenseCamera
from gscan.capture.motion import Coverage, MotionParams, MotionTracker
from gscan.capture.record import CaptureOptions, CaptureResult, FrameUpdate, run_capture

__all__ = ["CameraFrame", "CameraOptions", "CaptureOptions", "CaptureResult", "Coverage", "FrameUpdate",
           "MotionParams", "MotionTracker", "RealSenseCamera", "run_capture"]
