"""A scan's input and output opened and checked before any stage runs (`open_scan`): the output's path, the
template appended to or the partial database resumed, the captures' layouts and calibrations. Light (no numba,
scipy or open3d): a bad input is refused in one line before the pipeline loads (`gscan.scanning.pipeline.run_scan`
continues from an `OpenedScan`)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from gscan.errors import InputError
from gscan.io.captures import CaptureInput, capture_inputs
from gscan.io.output import Output, check_output
from gscan.scanning.options import ScanOptions
from gscan.scanning.output import open_appended, open_resumed
from gscan.template.db import TemplateDB

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence
    from gscan.io.sequence import Sequence as FrameSequence


@dataclass
class OpenedScan:
    """What `open_scan` opened: the captures (each with its opened frames and the prefix of its frames' names),
    every input frame's fingerprint by its prefixed name (`Sequence.fingerprints`), whether the scan resumes its
    output, and the database appended to or resumed with the output that replaces it (None for a new output)."""

    sources: list[Path]
    output: Path
    captures: list[tuple[CaptureInput, FrameSequence | RecordingSequence, str]]
    fingerprints: dict[str, dict[str, str] | None]
    resumed: bool
    db: TemplateDB | None = None
    target: Output | None = None

    def discard(self) -> None:
        """Close what was opened, the existing output left as it was (a scan that does not run after all)."""
        if self.db is not None:
            self.db.close()
        if self.target is not None:
            self.target.discard()


def open_scan(sources: Path | Sequence[Path], output: Path, opts: ScanOptions) -> OpenedScan:
    """Check the output and open the captures, in the order a scan refuses them: the output's path, the template
    appended to, the captures (`gscan.io.captures.capture_inputs`, then each one's layout), the partial database
    resumed. InputError naming the file; nothing is left open on failure."""
    sources = [sources] if isinstance(sources, Path) else [Path(s) for s in sources]
    resumed = opts.resume and output.is_file()
    check_output(output, force=opts.force or resumed or opts.append, kind=".gscan file path", fix="resume")
    opened = OpenedScan(sources, output, [], {}, resumed)
    try:
        if opts.append:
            opened.db, opened.target = open_appended(output, opts)
        taken = capture_names(opened.db) if opened.db is not None and opts.append else []
        inputs = capture_inputs(sources, opts.obj_id, taken)
        several = len(inputs) > 1 or opts.append
        opened.captures = [(c, open_capture(c, opts), f"{c.name}/" if several else "") for c in inputs]
        opened.fingerprints = {prefix + n: fp for _, seq, prefix in opened.captures
                               for n, fp in seq.fingerprints().items()}
        if resumed:
            opened.db, opened.target = open_resumed(sources, output, opts,
                                                    None if several else opened.captures[0][1], opened.fingerprints)
    except BaseException:
        opened.discard()
        raise
    return opened


def open_capture(c: CaptureInput, opts: ScanOptions) -> FrameSequence | RecordingSequence:
    """A capture's frames, opened (its layout and calibration read; no frame yet). InputError naming it."""
    from gscan.io import open_sequence

    obj_id = opts.obj_id if c.obj_id is None else c.obj_id
    seq = open_sequence(c.source, format=c.format or opts.format, intrinsics=opts.intrinsics,
                        depth_scale=opts.depth_scale, obj_id=obj_id, color_topic=opts.color_topic,
                        depth_topic=opts.depth_topic, depth_camera=opts.depth_camera)
    if obj_id is not None and seq.format != "bop":
        raise InputError(c.source, f"an object id is for BOP scene folders, this is a {seq.format} folder")
    if obj_id is not None and seq.gt_T_cam_obj is None:
        raise InputError(c.source / "scene_gt.json", "not found (the object id picks an object of its "
                         "poses)", fix="obj_id")
    if obj_id is not None and not seq.gt_T_cam_obj:
        raise InputError(c.source / "scene_gt.json", f"holds no pose of object {obj_id}", fix="obj_id")
    return seq


def capture_names(db: TemplateDB) -> list[str]:
    """The names of the captures a template was scanned from."""
    return [c["name"] for c in template_captures(db)]


def template_captures(db: TemplateDB) -> list[dict]:
    """A template's "captures" meta; a template of one capture: that capture, named after its input."""
    caps = db.get_meta("captures") or []
    if caps:
        return list(caps)
    src = db.get_meta("input")
    views = db.views()
    return [{"name": (Path(src).stem if Path(src).suffix else Path(src).name) or "capture", "input": src,
             "mode": db.get_meta("mode"), "frames": len(views),
             "registered": sum(v.T_obj_cam is not None for v in views), "joined": True, "reason": None,
             "T_obj_world": None}]
