"""A scan's output database: its meta (what a resumed scan must agree on), a new one, or the interrupted one resumed.

- `scan_meta(sources, options) -> dict`: the meta, `RESUME_KEYS` the values a resumed scan must agree on
- `create_output(output, options, meta) -> (TemplateDB, Output | None)`: a new database
- `open_resumed(sources, output, options, seq, fingerprints) -> (TemplateDB, Output | None)`: the interrupted one
- `open_appended(output, options) -> (TemplateDB, Output)`: a finished template, copied to be appended to
"""
from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from gscan.errors import InputError, OutputExists
from gscan.io.output import Output, journal_fits, occupied
from gscan.io.sequence import Sequence
from gscan.scanning.config import ScanConfig
from gscan.scanning.options import ScanOptions
from gscan.template.db import TemplateDB

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence

log = logging.getLogger(__name__)

RESUME_KEYS = ("input", "format", "intrinsics_sha256", "depth_scale_option", "config", "mode_option", "segment",
               "obj_id_option", "topics_option", "depth_camera")


def scan_meta(sources: list[Path], opts: ScanOptions) -> dict:
    """The database's meta; a resumed scan must agree on every RESUME_KEYS value (what changes its result):
    the inputs (one path, or the list of a scan of several captures), the layout as detected (`--format auto` and
    the named layout agree), the calibration files' contents."""
    from gscan.io import detect_format
    from gscan.io.captures import is_onboarding

    def fmt(source: Path) -> str:  # a BOP dataset folder's onboarding captures are BOP scene folders
        if opts.format != "auto":
            return opts.format
        return "bop" if is_onboarding(source) else detect_format(source)

    one = len(sources) == 1
    return {"source": "scan",
            "input": str(sources[0].resolve()) if one else [str(s.resolve()) for s in sources],
            "format": fmt(sources[0]) if one else [fmt(s) for s in sources],
            "intrinsics_sha256": None if opts.intrinsics is None else _sha256(Path(opts.intrinsics)),
            "depth_scale_option": opts.depth_scale, "config": opts.config.model_dump(), "mode_option": opts.mode,
            "segment": opts.segment, "obj_id_option": opts.obj_id, "descriptor": opts.config.features.kind,
            "topics_option": None if opts.color_topic is None and opts.depth_topic is None else
            [opts.color_topic, opts.depth_topic],
            "depth_camera": None if opts.depth_camera is None else opts.depth_camera.to_dict(),
            "units": "m"}


def _sha256(path: Path) -> str:
    import hashlib

    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as e:
        raise InputError(path, f"cannot read the calibration file ({e.strerror or e})") from None


def open_resumed(sources: list[Path], output: Path, opts: ScanOptions, seq: Sequence | RecordingSequence | None,
                 frames: dict) -> tuple[TemplateDB, Output | None]:
    """The interrupted scan's database; it must come from the same inputs, configuration and input frames
    (`frames`: `Sequence.fingerprints`, of every capture; `seq`: the one capture's frames, which name a changed
    file, or None). A complete database (or one whose journal would have too long a
    name) is continued in a copy renamed over it at the end, so a failed run leaves it as it was."""
    meta = scan_meta(sources, opts)
    db = TemplateDB.open(output, require_complete=False)  # read only until it is known to be continued
    try:
        stored = {k: db.get_meta(k) for k in RESUME_KEYS}
        # settings added to the configuration since the scan started take their defaults; a configuration this
        # version does not read differs
        with contextlib.suppress(ValueError, TypeError):
            stored["config"] = json.loads(json.dumps(ScanConfig.model_validate(stored["config"]).model_dump()))
        now = {k: json.loads(json.dumps(meta[k])) for k in stored}
        differ = [k for k in stored if stored[k] != now[k]]
        if differ and differ != ["input"]:
            raise InputError(output, f"was written from another input or configuration ({_differences(differ)})",
                             fix="restart")
        try:
            _check_frames(output, db.get_meta("input_frames"), json.loads(json.dumps(frames)), seq)
        except InputError as e:
            if differ:  # another capture at another path
                raise InputError(output, f"was written from another input ({stored['input']}, now {now['input']}): "
                                 f"{e.reason}", fix="restart") from None
            raise
        in_place = db.status != "complete" and journal_fits(output)
    except BaseException:
        db.close()
        raise
    db.close()
    if differ:  # the same frames, byte for byte, at another path: the capture was moved
        log.warning("%s: the capture was moved (%s, now %s); its frames are the same: resuming", output,
                    stored["input"], now["input"])

    def moved(db: TemplateDB) -> TemplateDB:
        if differ:
            db.set_meta("input", meta["input"])
        return db

    if in_place:
        return moved(TemplateDB.open(output, require_complete=False, writable=True, wal=True)), None

    def continued(target: Output) -> TemplateDB:
        shutil.copyfile(output, target.open())
        return moved(TemplateDB.open(target.tmp, require_complete=False, writable=True, wal=True))

    return _beside(Output(output, force=True, kind=".gscan file path"), continued)


_KEY_WORDS = {"input": "the input", "format": "the input layout", "intrinsics_sha256": "the --intrinsics file",
              "depth_scale_option": "--depth-scale", "config": "the configuration", "mode_option": "--mode",
              "segment": "--no-segment", "obj_id_option": "--obj-id", "topics_option": "the image topics",
              "depth_camera": "the depth camera"}


def _differences(keys: list[str]) -> str:
    """What differs from the interrupted scan, in words (RESUME_KEYS)."""
    return ", ".join(f"{_KEY_WORDS.get(k, k)} differs" for k in keys)


def open_appended(output: Path, opts: ScanOptions) -> tuple[TemplateDB, Output]:
    """The scanned template at `output`, copied beside it for captures to be appended to (`--append`); the copy
    replaces it once complete, so a failed or refused append leaves it as it was. InputError: no complete scanned
    template there, or one scanned with another configuration or segmentation (its views and the new ones would
    not be alike)."""
    if not output.is_file():
        raise InputError(output, "no template to append to (scan the first capture without --append)")
    with TemplateDB.open(output) as db:
        if db.get_meta("source") != "scan":
            raise InputError(output, "is not a scanned template: captures are appended to a scan's template only")
        config = db.get_meta("config")
        with contextlib.suppress(ValueError, TypeError):
            config = json.loads(json.dumps(ScanConfig.model_validate(config).model_dump()))
        if [config, db.get_meta("segment")] != json.loads(json.dumps([opts.config.model_dump(), opts.segment])):
            raise InputError(output, "was scanned with another configuration or segmentation: captures appended to "
                             "it must be scanned alike (--config, --no-segment as then)")

    def continued(target: Output) -> TemplateDB:
        shutil.copyfile(output, target.open())
        return TemplateDB.open(target.tmp, writable=True, wal=True)

    return _beside(Output(output, force=True, kind=".gscan file path"), continued)


def _beside(target: Output, make: Callable[[Output], TemplateDB]) -> tuple[TemplateDB, Output]:
    """(the database `make` writes at the temporary sibling `target`, target); on failure the sibling is removed
    and the error told as the output's (`Output.translate`)."""
    try:
        return make(target), target
    except BaseException as e:
        target.discard()
        t = target.translate(e)
        if t is not e:
            raise t from None
        raise


def _check_frames(output: Path, stored: object, frames: dict, seq: Sequence | RecordingSequence | None) -> None:
    """InputError unless the input frames hold what they held when the partial scan `output` started (their
    files' sizes and hashes): a scan resumed on other images would mix their keypoints and edges."""
    if not isinstance(stored, dict):
        raise InputError(output, "holds no record of the input frames it was started from (written by an older "
                         "gscan); it cannot be resumed safely", fix="restart")
    if stored == frames:
        return
    from gscan.io.layouts import natural_key

    for name in sorted(set(stored) | set(frames), key=natural_key):
        old, new = stored.get(name, "absent"), frames.get(name, "absent")
        if old == new:
            continue
        if new == "absent":
            what = f"frame {name} is no longer in the input"
        elif old == "absent":
            what = f"frame {name} was not in the input"
        elif old is None or new is None:
            what = f"frame {name} {'was unusable then' if old is None else 'is unusable now'}"
        else:
            role = next((r for r in ("color", "depth", "mask") if old.get(r) != new.get(r)), None)
            if role is None or not isinstance(seq, Sequence):  # a recording: one fingerprint of the frame's messages
                what = f"frame {name} changed"
            else:
                changed = getattr(seq.files(name), role) if role in new else None
                what = f"{changed} changed" if changed is not None else f"frame {name} has no {role} image now"
        raise InputError(output, f"the input frames are not the ones this partial scan was started from ({what})",
                         fix="restart")


def create_output(output: Path, opts: ScanOptions, meta: dict) -> tuple[TemplateDB, Output | None]:
    """A new database: in place while nothing is at the output (an interrupted scan is then resumed from it),
    else in a temporary sibling that replaces the old output once complete (`Output`)."""
    if not occupied(output) and journal_fits(output):
        try:
            return TemplateDB.create(output, meta=meta, wal=True), None
        except OutputExists as e:  # created by another process since the checks
            if not opts.force:
                raise OutputExists(output, e.reason, fix="resume") from None
    return _beside(Output(output, force=opts.force, kind=".gscan file path", fix="resume"),
                   lambda target: TemplateDB.create(target.open(), force=True, meta=meta, wal=True))
