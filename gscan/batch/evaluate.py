"""`run_batch_eval(...)`: score many templates against their scenes on Ray, into one BOP19 CSV.

Pairs (template, scenes), for a lab's catalogue:
- by name: every `NAME.gscan` directly in `templates_dir` with the folder `scenes_dir/NAME` (one scene, or a
  folder of scenes, as `gscan eval` reads them); templates without scenes and scene folders without a template
  are listed in the report, not scored;
- by a manifest, a CSV file with a header row: `template,scenes` and, optionally, `obj_id`, `model`,
  `gt_capture` and `name` (a template may be paired with several scene folders, and a scene folder with
  several templates: a BOP scene holds many objects). Relative paths are taken from the manifest's folder;
  empty cells are left out; a line whose first cell starts with `#` is a comment.
An object's id in the CSV: the manifest's `obj_id`, else the one the template was scanned for (a BOP scan's),
else the number in a BOP-style name (`obj_000005` -> 5), else the first free id in the pairs' order. Two
templates with one id are refused (the CSV could not tell them apart).

Each pair is one Ray task: `gscan.evaluate.bop19.evaluate` (what `gscan eval` runs) in a child process
(`gscan.batch.jobs`). The driver joins the pairs' rows into one BOP19 CSV (`scene_id,im_id,obj_id,score,R,t,
time`), with each image's time the sum of the times spent on it for every object scored in it (the BOP
toolkit requires one time per image), and writes the metrics per pair beside it (`<csv stem>.objects.json`
and `.objects.csv`). A pair that fails (bad input, a crash) is reported and the others go on; all three files
are written once every pair has ended, each replacing an old one (with `force`) only when complete.

Pooled over the pairs, the BOP19 average recalls are the means of the pairs' recalls weighted by their
images with ground truth (each recall is a mean over targets, so this is the recall over all targets).
"""
from __future__ import annotations

import csv
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gscan.batch.driver import (
    BatchMonitor,
    BatchState,
    batch_exit_code,
    fill_row,
    gscan_version,
    job_row_json,
    run_on_ray,
    write_csv,
    write_json,
)
from gscan.batch.runtime import MAX_RETRIES, TASK_CPUS, require_ray
from gscan.errors import InputError, not_a_file
from gscan.evaluate.bop19 import CSV_HEADER
from gscan.io.output import check_not_input, check_output, real_path
from gscan.template.db import TemplateDB

MANIFEST_COLUMNS = ("template", "scenes", "obj_id", "model", "gt_capture", "name")
AR_KEYS = ("AR", "AR VSD", "AR MSSD", "AR MSPD")
OBJECTS_HEADER = ("name", "obj_id", "status", "images", "found", "gt_images", "wrong_accepted", *AR_KEYS, "AUC ADD",
                  "AUC ADD-S", "mean time ms", "seconds", "peak_rss_mb", "error", "template", "scenes")
_BOP_NAME = re.compile(r"^obj_0*(\d+)$")
# what an evaluation job's result gives its row (`gscan.batch.child`)
ROW_KEYS = ("images", "found", "gt_images", "wrong_accepted", "diameter_m", "metrics")


@dataclass
class Pair:
    """A template to score over a scene folder, with the object id it has in the CSV."""

    name: str
    template: Path
    scenes: Path
    obj_id: int | None = None
    model: Path | None = None
    gt_capture: Path | None = None


@dataclass
class PairRow:
    """The report's row of a pair: its images, found poses, images with ground truth, found poses that are
    wrong (ADD above 10 % of the object's diameter), the metrics of `gscan eval` (percent), seconds and
    the evaluation process's peak memory; a failure's one-line error (`error_kind` as in a batch scan)."""

    name: str
    template: str
    scenes: str
    obj_id: int
    status: str
    attempts: int = 0
    images: int | None = None
    found: int | None = None
    gt_images: int | None = None
    wrong_accepted: int | None = None
    diameter_m: float | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    peak_rss_bytes: int | None = None
    error: str | None = None
    error_kind: str | None = None
    fix: str | None = None
    node: str | None = None

    def to_json(self) -> dict[str, Any]:
        return job_row_json(self)

    def csv_row(self) -> list[Any]:
        m = self.metrics

        def blank(x: Any) -> Any:
            return "" if x is None else x

        def num(k: str) -> str:
            return f"{m[k]:.2f}" if k in m else ""

        return [self.name, self.obj_id, self.status, blank(self.images), blank(self.found), blank(self.gt_images),
                blank(self.wrong_accepted), *(num(k) for k in AR_KEYS), num("AUC ADD"), num("AUC ADD-S"),
                num("mean time ms"), f"{self.seconds:.2f}",
                "" if self.peak_rss_bytes is None else f"{self.peak_rss_bytes / 2**20:.1f}", self.error or "",
                self.template, self.scenes]


@dataclass
class BatchEvalReport:
    """The pairs' rows, the CSV written, what was left unpaired, warnings, and where it ran."""

    output: Path
    rows: list[PairRow]
    unpaired_templates: list[str]
    unpaired_scenes: list[str]
    warnings: list[str]
    seconds: float
    runtime: str | None
    capacity: int

    @property
    def exit_code(self) -> int:
        return batch_exit_code(self.rows)

    def summary(self) -> dict[str, Any]:
        done = [r for r in self.rows if r.status == "evaluated"]
        pooled: dict[str, float | None] = {}
        for k in AR_KEYS:
            have = [r for r in done if k in r.metrics and r.gt_images]
            n = sum(r.gt_images or 0 for r in have)
            pooled[k] = (sum((r.gt_images or 0) * r.metrics[k] for r in have) / n
                         if have and len(have) == len(done) and n else None)
        images = sum(r.images or 0 for r in done)
        return {"pairs": len(self.rows), "evaluated": len(done), "failed": len(self.rows) - len(done),
                "exit_code": self.exit_code, "images": images, "found": sum(r.found or 0 for r in done),
                "gt_images": sum(r.gt_images or 0 for r in done),
                "wrong_accepted": sum(r.wrong_accepted or 0 for r in done), "pooled": pooled,
                "seconds": round(self.seconds, 3), "runtime": self.runtime, "cpus": self.capacity,
                "cpus_per_task": TASK_CPUS, "max_retries": MAX_RETRIES, "output": str(self.output),
                "unpaired_templates": self.unpaired_templates, "unpaired_scenes": self.unpaired_scenes,
                "warnings": self.warnings}

    def to_json(self) -> dict[str, Any]:
        """The `batch-eval --json` object: {"summary": {...}, "pairs": [row, ...]}."""
        return {"summary": self.summary(), "pairs": [r.to_json() for r in self.rows]}


def objects_paths(output_csv: Path) -> tuple[Path, Path]:
    """The per-object reports beside the CSV: `<stem>.objects.json` and `<stem>.objects.csv`."""
    return output_csv.with_suffix(".objects.json"), output_csv.with_suffix(".objects.csv")


# ------------------------------------------------------------------------------------------ pairs
def find_pairs(templates_dir: str | Path, scenes_dir: str | Path) -> tuple[list[Pair], list[str], list[str]]:
    """(pairs by name, templates without scenes, scene folders without a template); see the module docstring.
    InputError when a folder is missing or no name pairs."""
    templates_dir, scenes_dir = Path(templates_dir), Path(scenes_dir)
    for d, what in ((templates_dir, "templates folder"), (scenes_dir, "scenes folder")):
        if not d.is_dir():
            raise InputError(d, f"{what} not found" if not d.exists() else f"is not a folder (expected the {what})")
    templates = {p.stem: p for p in sorted(templates_dir.glob("*.gscan")) if p.is_file() and not p.name.startswith(".")}
    scenes = {p.name: p for p in sorted(scenes_dir.iterdir()) if p.is_dir() and not p.name.startswith(".")}
    pairs = [Pair(n, templates[n], scenes[n]) for n in templates if n in scenes]
    if not pairs:
        raise InputError(scenes_dir, f"holds no scene folder named as a template of {templates_dir} "
                         f"({len(templates)} templates, {len(scenes)} folders): pair them with a manifest")
    return pairs, [n for n in templates if n not in scenes], [n for n in scenes if n not in templates]


def read_manifest(path: str | Path) -> list[Pair]:
    """The pairs of a manifest CSV (see the module docstring); InputError naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "manifest")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read the manifest ({e.__class__.__name__})") from None
    lines = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(path, "the manifest is empty (expected a header row `template,scenes[,obj_id,...]`)")
    rows = []
    for n, ln in lines:  # each line on its own: an unclosed quote never swallows the lines after it
        try:
            rows.append(next(csv.reader([ln], strict=True)))
        except csv.Error as e:
            raise InputError(path, f"line {n}: not a CSV row ({e})") from None
    header = [h.strip().lower() for h in rows[0]]
    unknown = [h for h in header if h not in MANIFEST_COLUMNS]
    if unknown or "template" not in header or "scenes" not in header or len(set(header)) != len(header):
        raise InputError(path, f"line {lines[0][0]}: the header must name the columns template and scenes, and "
                         f"may name {', '.join(MANIFEST_COLUMNS[2:])} (got {','.join(rows[0])})")
    base = path.parent
    pairs: list[Pair] = []
    for (n, _), row in zip(lines[1:], rows[1:], strict=True):
        if len(row) != len(header):
            raise InputError(path, f"line {n}: {len(row)} cells for {len(header)} columns")
        cell = {h: v.strip() for h, v in zip(header, row, strict=True)}
        if not cell["template"] or not cell["scenes"]:
            raise InputError(path, f"line {n}: a template and a scenes folder are needed")
        obj_id = None
        if cell.get("obj_id"):
            try:
                obj_id = int(cell["obj_id"])
            except ValueError:
                obj_id = 0
            if not 1 <= obj_id < 2**31:
                raise InputError(path, f"line {n}: obj_id must be a positive integer, not {cell['obj_id']!r}")
        model, gt_capture = (base / cell[k] if cell.get(k) else None for k in ("model", "gt_capture"))
        pairs.append(Pair(cell.get("name") or "", base / cell["template"], base / cell["scenes"], obj_id, model,
                          gt_capture))
    if not pairs:
        raise InputError(path, "the manifest names no pair")
    _name_pairs(pairs, path)
    return pairs


def _name_pairs(pairs: list[Pair], manifest: Path) -> None:
    """Give the unnamed pairs a name: the template's, with the scene folder's where a template repeats."""
    stems = [p.template.stem for p in pairs]
    for p in pairs:
        if not p.name:
            p.name = p.template.stem if stems.count(p.template.stem) == 1 else f"{p.template.stem}@{p.scenes.name}"
    seen: dict[str, Pair] = {}
    for p in pairs:
        if p.name in seen:
            raise InputError(manifest, f"two pairs are named {p.name!r}: give them names (a name column)")
        seen[p.name] = p


def assign_obj_ids(pairs: list[Pair]) -> None:
    """Fill each pair's obj_id (see the module docstring); InputError when two templates share one."""
    by_template: dict[Path, int] = {}
    for p in pairs:  # given ones first
        if p.obj_id is not None:
            by_template.setdefault(real_path(p.template), p.obj_id)
    for p in pairs:  # then the template's own, then a BOP-style name
        key = real_path(p.template)
        if p.obj_id is None:
            p.obj_id = by_template.get(key) or _stored_obj_id(p.template) or _name_obj_id(p.template.stem)
        if p.obj_id is not None:
            by_template.setdefault(key, p.obj_id)
    taken = {p.obj_id for p in pairs if p.obj_id is not None}
    free = (i for i in range(1, 2**31) if i not in taken)
    for p in pairs:
        if p.obj_id is None:
            key = real_path(p.template)
            if key not in by_template:
                by_template[key] = next(free)
            p.obj_id = by_template[key]
    owner: dict[int, Path] = {}
    for p in pairs:
        assert p.obj_id is not None
        other = owner.setdefault(p.obj_id, real_path(p.template))
        if other != real_path(p.template):
            raise InputError(p.template, f"has object id {p.obj_id}, as {other} has: give each template its own "
                             "obj_id (a manifest's obj_id column)")


def _stored_obj_id(template: Path) -> int | None:
    try:
        with TemplateDB.open(template, require_complete=False) as db:
            v = db.get_meta("obj_id")
    except InputError:
        return None  # the pair's task names what is wrong with it
    return v if isinstance(v, int) and v >= 1 else None


def _name_obj_id(name: str) -> int | None:
    m = _BOP_NAME.match(name)
    return int(m.group(1)) if m and int(m.group(1)) >= 1 else None


# ------------------------------------------------------------------------------------------ the batch
def _row(pair: Pair, res: dict[str, Any]) -> PairRow:
    assert pair.obj_id is not None
    status = "evaluated" if res.get("ok") else "failed"
    return fill_row(PairRow(pair.name, str(pair.template), str(pair.scenes), pair.obj_id, status), res, ROW_KEYS)


def describe_row(row: PairRow) -> str:
    """One line about a finished pair, for the progress display."""
    if row.status == "failed":
        return row.error or "failed"
    m = row.metrics
    parts = [f"obj {row.obj_id}", f"{row.found}/{row.images} found"]
    if "AR" in m:
        parts.append(f"AR {m['AR']:.1f}")
    elif "AR MSSD" in m:
        parts.append(f"AR MSSD {m['AR MSSD']:.1f}")
    if row.wrong_accepted:
        parts.append(f"{row.wrong_accepted} wrong")
    parts.append(f"{row.seconds:.1f} s")
    return ", ".join(parts)


def combined_csv(pairs: list[Pair], results: dict[str, dict[str, Any]]) -> tuple[str, list[str]]:
    """(the BOP19 CSV of every evaluated pair, warnings): rows in the pairs' order, each image's time the sum
    over the objects scored in it; a warning for scene ids that come from more than one scenes folder."""
    totals: dict[tuple[int, int], float] = {}
    folders: dict[int, set[str]] = {}
    for p in pairs:
        res = results.get(p.name) or {}
        if not res.get("ok"):
            continue
        for scene_id, im_id, t in res["image_times"]:
            totals[(int(scene_id), int(im_id))] = totals.get((int(scene_id), int(im_id)), 0.0) + float(t)
            folders.setdefault(int(scene_id), set()).add(str(real_path(p.scenes)))
    lines = [CSV_HEADER]
    for p in pairs:
        res = results.get(p.name) or {}
        if not res.get("ok"):
            continue
        for line in res["csv_lines"]:
            cells = line.split(",")
            cells[-1] = f"{totals[(int(cells[0]), int(cells[1]))]:.6f}"
            lines.append(",".join(cells))
    warnings = [f"scene id {s} comes from {len(f)} scenes folders ({', '.join(sorted(f))}): the BOP toolkit takes "
                "their images for one scene's" for s, f in sorted(folders.items()) if len(f) > 1]
    return "\n".join(lines) + "\n", warnings


def run_batch_eval(output_csv: str | Path, *, templates_dir: str | Path | None = None,
                   scenes_dir: str | Path | None = None, manifest: str | Path | None = None, refine: bool = True,
                   address: str | None = None, workers: int | None = None, force: bool = False,
                   monitor: BatchMonitor | None = None) -> BatchEvalReport:
    """Score every pair (by name: `templates_dir` with `scenes_dir`; or a `manifest`) on Ray into one BOP19
    CSV `output_csv` and the metrics per pair beside it (see the module docstring).

    Raises:
        RayMissing: Ray is not installed.
        InputError: an existing output without `force`, missing folders, a malformed manifest, two templates
            with one object id, no pair at all, a cluster that cannot be reached. A pair's bad input is its
            row's error, not an exception.
    """
    t0 = time.monotonic()
    output_csv = Path(output_csv)
    for path in (output_csv, *objects_paths(output_csv)):
        check_not_input(path, [templates_dir, scenes_dir, manifest])
    for path, kind in ((output_csv, ".csv file path"), *((p, "file path") for p in objects_paths(output_csv))):
        check_output(path, force=force, kind=kind)
    if (manifest is None) == (templates_dir is None or scenes_dir is None):
        raise ValueError("give either a manifest or both templates_dir and scenes_dir")
    if manifest is not None:
        pairs, lone_templates, lone_scenes = read_manifest(manifest), list[str](), list[str]()
    else:
        assert templates_dir is not None and scenes_dir is not None
        pairs, lone_templates, lone_scenes = find_pairs(templates_dir, scenes_dir)
    assign_obj_ids(pairs)
    require_ray()  # after the input checks: a bad input is refused without loading Ray
    jobs = [{"kind": "eval", "key": p.name, "template": str(p.template), "scenes": str(p.scenes), "obj_id": p.obj_id,
             "model": None if p.model is None else str(p.model),
             "gt_capture": None if p.gt_capture is None else str(p.gt_capture), "refine": refine,
             "version": gscan_version()} for p in pairs]
    by_name = {p.name: p for p in pairs}

    def describe(job: dict, res: dict) -> tuple[str, str]:
        row = _row(by_name[job["key"]], res)
        return row.status, describe_row(row)

    def announce(cpus: int) -> None:
        if monitor is not None:
            monitor.update(BatchState(total=len(jobs), queued=len(jobs), capacity=cpus))

    results, runtime, capacity = run_on_ray(address, workers, jobs, describe, monitor, announce)
    rows = [_row(p, results[p.name]) for p in pairs]
    text, warnings = combined_csv(pairs, results)
    report = BatchEvalReport(output_csv, rows, lone_templates, lone_scenes, warnings, time.monotonic() - t0, runtime,
                             capacity)
    from gscan.io.output import Output

    with Output(output_csv, force=force, kind=".csv file path") as out:
        out.tmp.write_text(text, encoding="utf-8")
    objects_json, objects_csv = objects_paths(output_csv)
    write_json(objects_json, report.to_json())
    write_csv(objects_csv, OBJECTS_HEADER, [r.csv_row() for r in rows])
    return report
