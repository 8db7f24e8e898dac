"""`gscan ros2`: the templates' poses on ROS 2 topics (the optional extra gscan[ros2]; docs/ros2.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from gscan.cli.output import UsageError, print_json, say, setup_logging
from gscan.cli.texts import ESTIMATE_CONFIG_HELP, JSON_HELP

#: the command takes ROS's own arguments after `--ros-args` (parameters, remappings, log levels)
ROS2_CONTEXT = {"allow_extra_args": True, "ignore_unknown_options": True}


def ros2(
    ctx: typer.Context,
    templates: list[Path] = typer.Argument(..., metavar="OBJ.gscan...", help="template databases to follow"),
    play: Path | None = typer.Option(
        None, "--play", help="publish this ROS 2 recording (rosbag2 folder, .db3 or .mcap) onto the node's topics, "
        "at its recorded pace, and stop after its last frame"),
    rate: float = typer.Option(1.0, "--rate", min=0.01, help="with --play: play this many times as fast"),
    config: Path | None = typer.Option(None, "--config", help=ESTIMATE_CONFIG_HELP),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP + " (the run's counts, when it ends)"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log details to stderr"),
) -> None:
    """Run a ROS 2 node that publishes the templates' poses (ROS parameters after --ros-args; docs/ros2.md)."""
    # the variadic argument takes what follows --ros-args too (click leaves unknown options among the arguments)
    words = [str(t) for t in templates] + list(ctx.args)
    cut = words.index("--ros-args") if "--ros-args" in words else len(words)
    templates, ros_args = [Path(w) for w in words[:cut]], words[cut:]
    if not templates:
        raise UsageError(None, "no template given (OBJ.gscan... come before --ros-args)")
    if unknown := [w for w in words[:cut] if w.startswith("-")]:
        raise UsageError(None, f"unknown option {unknown[0]!r} (ROS arguments follow --ros-args)")
    setup_logging(verbose)
    from gscan.ros2 import require_rclpy

    require_rclpy()  # before any template loads: the one line that names the extra
    from gscan.estimate.settings import load_estimate_params
    from gscan.ros2.node import load_templates
    from gscan.ros2.run import run
    from gscan.ros2.settings import check_ros_args

    check_ros_args(ros_args)  # before the templates load

    if play is not None and not play.exists():
        raise UsageError(play, "recording not found")
    tracks = load_templates(templates, load_estimate_params(config))

    def ready(node: Any, player: Any) -> None:
        ns = node.get_fully_qualified_name()
        say("ROS 2 node ", (ns, "bold"), f" follows {', '.join(t.name for t in tracks)}: colour "
            f"{node.params.color_topic}, depth {node.params.depth_topic}; poses on {ns}/<template>/pose, status on "
            f"{ns}/status" + (f"; playing {play}" if player is not None else " (Ctrl+C to stop)"))

    out = run(tracks, ros_args, play=play, rate=rate, on_ready=ready)
    if json_out:
        print_json(out)
        return
    poses = ", ".join(f"{k} {v}" for k, v in out["with_pose"].items())
    say((f"{out['processed']} frames processed", "bold"),
        (f" of {out['played']} played" if "played" in out else ""),
        f": {out['dropped']} dropped while busy, {out['unpaired']} images without a partner; with a pose: {poses}; "
        f"latency median {out['latency_ms']['median']:.0f} ms")
    for problem in out["problems"]:
        say(("input refused:", "yellow"), f" {problem}")
