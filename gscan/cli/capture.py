"""`gscan capture`: record a capture folder from a RealSense camera or a recording."""
from __future__ import annotations

from pathlib import Path

import typer

from gscan.cli.output import UsageError, print_json, say, say_interrupted, setup_logging
from gscan.cli.texts import JSON_HELP, RS_PLAYBACK_HELP


def capture(
    output: Path = typer.Option(..., "-o", "--output", help="capture folder to write (rgb/, depth/, cam_K.txt)"),
    from_file: Path | None = typer.Option(None, "--from", help=RS_PLAYBACK_HELP),
    fps: int | None = typer.Option(None, "--fps", min=1, max=1000,
                                   help="stream rate (live: 30 by default; --from: the recording's)"),
    every: int | None = typer.Option(None, "--every", min=1, help="keep every Nth frame instead of the motion rule"),
    width: int | None = typer.Option(None, "--width", min=1, help="stream width (live: 640 by default)"),
    height: int | None = typer.Option(None, "--height", min=1, help="stream height (live: 480 by default)"),
    min_motion: float = typer.Option(10.0, "--min-motion", min=0.1, max=90.0,
                                     help="degrees the view of the object must turn for a frame to be kept"),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="stop after keeping this many frames"),
    real_time: bool = typer.Option(False, "--real-time", help="--from: play at the recorded pace"),
    align: str = typer.Option("gscan", "--align", help="depth-to-colour alignment: gscan|librealsense (rs.align)"),
    preview: bool | None = typer.Option(None, "--preview/--no-preview",
                                        help="live preview in the browser (default: on live, off with --from)"),
    host: str = typer.Option("127.0.0.1", "--host", help="preview address to bind"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="preview port"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Record a capture folder from a RealSense camera (or a recording): the frames that moved enough, or every Nth.

    Ctrl+C ends the capture; the folder then holds the frames kept so far, a capture `gscan scan` reads."""
    from dataclasses import replace

    setup_logging(verbose)
    if (width is None) != (height is None):
        raise UsageError(None, "--width and --height go together")
    if align not in ("gscan", "librealsense"):
        raise UsageError(None, f"--align must be gscan or librealsense, not {align!r}")
    from gscan.capture.folder import check_capture_output

    check_capture_output(output, from_file)  # a bad output is refused before the camera's libraries load
    from gscan.capture import CameraOptions, CaptureOptions, MotionParams, RealSenseCamera, run_capture

    opts = CaptureOptions(every=every, motion=replace(MotionParams(), min_angle_deg=min_motion), max_frames=max_frames)
    camera = RealSenseCamera(from_file, CameraOptions(width=width, height=height, fps=fps, real_time=real_time,
                                                      align=align))
    show = preview if preview is not None else from_file is None
    viewer = None
    if show:
        from gscan.viewer.capture_preview import CapturePreview

        camera.check()  # a missing camera is named before the preview starts
        viewer = CapturePreview(host, port)
        say("preview at ", (viewer.url, "bold"))
    from gscan.signals import stop_on

    try:
        with stop_on() as stop:  # the first Ctrl+C ends the capture; a second one aborts
            result = run_capture(camera, output, opts, stop=stop, on_frame=viewer.update if viewer else None)
    except KeyboardInterrupt:
        say_interrupted("interrupted: nothing was written")
        raise
    finally:
        if viewer is not None:
            viewer.stop()
    if json_out:
        print_json(result.to_json())
        return
    how = "stopped: " if result.interrupted else ""
    say(f"{how}captured {len(result.kept)} frames (of {result.seen} seen) into {result.output}; "
        f"{result.covered} of {result.directions} viewing directions covered")
    for number, why in result.left_out.items():
        say(("left out:", "yellow"), f" colour frame {number}: {why}")
    if result.skipped:
        why = ("played at the recorded pace, frames read too slowly are dropped as a live camera's are" if real_time
               else "play it again, or scan the recording itself")
        say(("skipped:", "yellow"), f" the SDK's playback never delivered {len(result.skipped)} of the recording's "
            f"frames ({', '.join(result.skipped)}, as scan names them): {why}")
    for words in result.missing:
        say(("missing:", "yellow"), f" {words}")
