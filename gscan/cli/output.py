"""What the command line prints: one line on stderr (`say`, `line`, control characters escaped), one JSON object
on stdout (`print_json`), the one line an error is reported with (`error_line`), poses and matrices as text.
stdout holds only `--json` objects (and `config dump`); everything else goes to stderr."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

from rich.console import Console

from gscan.errors import InputError

# no markup or emoji codes: file and frame names ("[x]", ":smile:") are printed as they are; styles go through `say`
err = Console(stderr=True, highlight=False, markup=False, emoji=False, soft_wrap=True)

# characters that would act on the terminal instead of being shown (ANSI escape sequences, carriage returns,
# line breaks, bidirectional overrides): names from files and templates are printed with these escaped
_BIDI = "\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069\u2028\u2029"
_UNPRINTABLE = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))} | {
    ord(c): f"\\u{ord(c):04x}" for c in _BIDI} | {ord("\n"): "\\n", ord("\r"): "\\r", ord("\t"): "\\t"}


def printable(text: object) -> str:
    """`text` as one line that shows what it holds: control characters written as \\x1b, \\n, \\u202e."""
    return str(text).translate(_UNPRINTABLE)


def say(*parts: str | tuple[str, str]) -> None:
    """One line on stderr; a (text, style) part is styled, a str part printed as it is (control characters
    escaped: names come from files and templates)."""
    from rich.text import Text

    text = Text()
    for p in parts:
        s, style = p if isinstance(p, tuple) else (p, None)
        text.append(printable(s), style)
    err.print(text)


def line(text: object) -> None:
    """One line of plain text on stderr, control characters escaped."""
    err.print(printable(text))


def plain(text: str) -> None:
    """Text on stderr as it is, without markup or highlighting (error and interruption lines)."""
    err.print(text, markup=False, highlight=False, soft_wrap=True)


# the option or command that addresses an InputError's `fix` (gscan.errors.FIXES)
_FIXES = {
    "replace": "pass --force to replace it",
    "resume": "pass --resume to continue it or --force to replace it",
    "restart": "pass --force to start over",
    "finish": "run `gscan scan --resume` to finish it",
    "depth_scale": "pass --depth-scale",
    "intrinsics": "pass --intrinsics (cam_K.txt or an Open3D camera JSON)",
    "obj_id": "choose the object with --obj-id",
    "gt_capture": "pass --gt-capture with the capture (rgb/, depth/, annotated_poses/ or scene_gt.json) to relate "
                  "it to the ground truth",
    "port": "choose another --port",
    "host": "choose another --host",
    "output": "choose another output with -o",
    "roi": "--roi takes X,Y,W,H: a box inside the first frame, in pixels",
    "mask": "--mask takes a mask image of the first frame (its size, non-zero on the object)",
}


def object_line(obj: dict) -> str:
    """The object segmentation chose (the "object" of `scan --json` / `info --json`) in one line."""
    length, width, height = obj["size_m"]
    by = {"roi": "the --roi box", "mask": "the --mask"}.get(obj["by"], "where the views look")
    share = "" if obj["by"] == "fixation" else f" (at the centre of {obj['centre_share']:.0%} of the views)"
    return f"object: {length:.2f} x {width:.2f} m, {height:.2f} m high, chosen by {by}: {obj['reason']}{share}"


def error_line(e: BaseException) -> str:
    """The one line an error is reported with: its message (control characters escaped) and, for an
    InputError with a `fix`, the option of this CLI that addresses it."""
    fix = _FIXES.get(getattr(e, "fix", None) or "")
    return printable(f"error: {e}" + (f"; {fix}" if fix else ""))


class UsageError(InputError):
    """Bad command-line usage that names a file or option (exit 2)."""


def print_json(obj: Any) -> None:
    """The one JSON object of `--json` on stdout (numpy values and paths as JSON values)."""
    sys.stdout.write(json.dumps(obj, indent=None, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def format_matrix(T: list[list[float]]) -> str:
    """A matrix as indented rows of signed numbers, one row a line."""
    return "\n".join("  [" + " ".join(f"{x:+.5f}" for x in row) + "]" for row in T)


def format_pose(T: Any) -> str:
    """One line: translation (m) and rotation as an angle (deg) about a unit axis, e.g.
    `t = [+0.1000, -0.0200, +0.5000] m, R = 30.00 deg about [+0.000, +0.000, +1.000]`."""
    import cv2
    import numpy as np

    T = np.asarray(T, dtype=np.float64)
    rotvec = cv2.Rodrigues(T[:3, :3])[0].reshape(3)
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    t = T[:3, 3]
    return (f"t = [{t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}] m, "
            f"R = {np.degrees(angle):.2f} deg about [{axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f}]")


def part_lines(parts: list[list[str]]) -> None:
    """One line per separate part of a scanned capture (`poses`, `info`)."""
    for k, part in enumerate(parts, 1):
        line(f"separate part {k}: {len(part)} frames ({', '.join(part)}), not joined to the registered ones")


def coverage_text(coverage: dict[str, Any] | None) -> list[str]:
    """The lines naming a template's coverage of viewing directions (the `"coverage"` JSON object; None: a template
    made before coverage was recorded): the share seen, then each missing region with what to do."""
    if coverage is None:
        return ["coverage: unknown (the template was made before coverage was recorded)"]
    return ([f"coverage: {coverage['share']:.0%} of the viewing directions seen"]
            + [f"missing: {m}" for m in coverage["missing"]])


def coverage_lines(coverage: dict[str, Any] | None) -> None:
    """`coverage_text`, a `line` each (`info`)."""
    for text in coverage_text(coverage):
        line(text)


class _PrintableFormatter(logging.Formatter):
    """Log lines with control characters escaped (frame and file names come from the input)."""

    def format(self, record: logging.LogRecord) -> str:
        return printable(super().format(record))


def symmetry_texts(sym: dict) -> list[str]:
    """A text per symmetry of a "symmetries" JSON object (`info`, `scan --json`): the axis of revolution with a point
    on it (mm), each turn's angle and axis (object frame), and whether it holds in the texture too; ["none found"]
    without any."""
    import numpy as np

    from gscan.geometry.symmetry import Symmetries, turn_of

    s = Symmetries.from_json(sym)

    def vec(x: np.ndarray, scale: float = 1.0) -> str:
        return "(" + ", ".join(f"{float(c) * scale + 0.0:.3g}" for c in x) + ")"

    def held(t: bool) -> str:
        return "shape and texture" if t else "shape only"

    out = [f"revolution about axis {vec(a)} through {vec(o, 1000.0)} mm ({held(t)})"
           for (a, o), t in zip(s.continuous, s.continuous_in_texture, strict=True)]
    for S, t in zip(s.discrete, s.discrete_in_texture, strict=True):
        axis, angle = turn_of(S)
        out.append(f"{angle:.0f} deg about axis {vec(axis)} ({held(t)})")
    return out or ["none found"]


def setup_logging(verbose: bool) -> None:
    """Log lines on stderr: INFO and up with -v, else warnings and errors."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_PrintableFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler])


_interrupt_said = False


def say_interrupted(text: str) -> None:
    """The line a command prints when Ctrl+C stops it (what it left behind); `main` then prints no other."""
    global _interrupt_said
    plain(printable(text))
    _interrupt_said = True


def interrupt_said() -> bool:
    """Whether a command already said what its interruption left."""
    return _interrupt_said


def camera_line(cam: dict) -> tuple[tuple[str, str], str]:
    """The colour camera check's line (`scan`'s summary, `info`): kept or corrected with the estimate's interval, or
    the warning that it could not confirm the focal length (`gscan.scanning.camera.camera_report`)."""
    given, used = cam["given_focal_px"][0], cam["colour_focal_px"][0]
    lo, hi = (f"{x:g}" if x is not None else "?" for x in cam.get("interval_px", [None, None]))
    found = f"the texture of {cam['pairs']} frame pairs lines up best at {cam.get('estimate_px')} px ({lo}-{hi} px)"
    verdict = cam.get("verdict", "corrected" if cam["corrected"] else "kept")
    if verdict == "corrected":
        return (("colour camera:", "yellow"), f" the depth did not line up with the colour at the given focal length "
                f"{given:g} px; {found}: used {used:g} px ({cam['texture_agreement']['used']:.0%} of textured "
                f"tiles against {cam['texture_agreement']['given']:.0%}), with the given intrinsics as the depth "
                "camera's. --intrinsics and --depth-intrinsics set both cameras")
    if verdict == "kept":
        return (("colour camera:", "bold"), f" focal length given {given:g} px, checked, kept: {found}")
    return (("colour camera: warning:", "red"), f" {cam['warning']}")
