"""The template database: one SQLite file (`*.gscan`) per scanned object, schema version 1.

Like COLMAP's `database.db`, it keeps every input view (intrinsics, pose `T_obj_cam`, encoded
colour / depth / mask), per-view keypoints (pixels + 3D points in the OBJECT frame) with their
descriptors, the registration edges with their quality numbers, the fused mesh and cloud, grasps,
and a `meta` table of JSON values (schema, status, descriptor config, units, source, config).

Durability: rollback journal with `synchronous=FULL`; every write method is one transaction, so
a crash loses at most the record being written. A writer of many records (the scan) opens the file with
`wal=True` (write-ahead log, `synchronous=NORMAL`: a commit costs no fsync) and groups its writes in
`batch()` transactions, one per stage or chunk of a stage: a crash loses at most the uncommitted batch, never
the file's consistency. Closing a WAL writer turns the file back into a rollback-journal database, so a
finished template is one self-contained file that any SQLite reader opens, also from a read-only folder.
Readers leave the journal mode as they find it. While a scan runs the status is "partial"; the
scan's last transaction (`mark_complete`) makes it "complete". Consumers (`estimate`, `export`,
`view`) open with `require_complete=True` and are refused a partial database.

Arrays are stored with `np.save` (dtype and shape included, bit-exact). Colour is JPEG q90 or
PNG (`color_codec`), depth a 16-bit PNG in millimetres (0 = invalid, sub-millimetre detail and
depths beyond 65.535 m are lost), masks an 8-bit PNG (0/255); `gscan.template.codec` encodes them. A
value that does not decode makes the read an InputError naming the database.

Keypoint frame rule: a view's keypoint points are in the object frame when the view has a pose;
for an unregistered view (`T_obj_cam` None) they are in its camera frame. `update_pose` re-expresses
the stored points so this stays true. Edge `matches` index the stored keypoints of src and tgt.
"""
from __future__ import annotations

import functools
import json
import logging
import os
import sqlite3
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, Concatenate, ParamSpec, TypeVar

import cv2
import numpy as np

from gscan.errors import GscanError, InputError, not_a_file
from gscan.features import Features
from gscan.geometry.coverage import CoverageMap
from gscan.geometry.mesh import MeshData, to_u8_colors
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import is_rigid
from gscan.io.camera import Intrinsics
from gscan.io.images import image_too_large
from gscan.io.output import SQLITE_SIDECARS, Output, file_identity, remove_sqlite_sidecars, write_failure_reason
from gscan.registration.edge import Edge
from gscan.template.codec import (
    BadBlob,
    TooLarge,
    check_colors,
    check_keypoints,
    check_mesh,
    check_T,
    decode_array,
    decode_image,
    decode_json,
    decode_T,
    encode_array,
    encode_color,
    encode_depth,
    encode_mask,
)
from gscan.template.records import Template, TemplateSummary, View

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
# keypoint sets of a view: "registration" (what its edges' matches index; whole frame for a static
# object) and "object" (on the object only, for pose estimation; a scan adds them to its keyframes)
FEATURE_ROLES = ("registration", "object")
APPLICATION_ID = 0x6753434E  # "gSCN", PRAGMA application_id of every gscan database
_SQLITE_MAGIC = b"SQLite format 3\x00"
# SQLite's primary result codes (the sqlite3 module names them only from Python 3.11; the values are SQLite's)
_SQLITE_BUSY, _SQLITE_LOCKED, _SQLITE_READONLY, _SQLITE_IOERR, _SQLITE_FULL, _SQLITE_CANTOPEN = 5, 6, 8, 10, 13, 14
_SQLITE_READONLY_DBMOVED = 1032  # SQLITE_READONLY | (4 << 8): the file was unlinked or renamed under the connection

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE views (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, input_index INTEGER,
    intrinsics TEXT NOT NULL, T_obj_cam BLOB, color BLOB, color_codec TEXT, depth BLOB, mask BLOB,
    keyframe INTEGER NOT NULL, quality REAL);
CREATE TABLE features (
    view_id INTEGER NOT NULL REFERENCES views(id), role TEXT NOT NULL, kind TEXT NOT NULL, n INTEGER NOT NULL,
    pixels BLOB NOT NULL, points BLOB NOT NULL, descriptors BLOB NOT NULL, scales BLOB,
    PRIMARY KEY (view_id, role));
CREATE TABLE edges (
    id INTEGER PRIMARY KEY, src TEXT NOT NULL, tgt TEXT NOT NULL, T_tgt_src BLOB, matches BLOB NOT NULL,
    cost REAL, rmse REAL, fitness REAL, kind TEXT NOT NULL, accepted INTEGER NOT NULL, reason TEXT,
    UNIQUE (src, tgt));
CREATE TABLE mesh (id INTEGER PRIMARY KEY CHECK (id = 1), vertices BLOB NOT NULL, triangles BLOB NOT NULL,
    colors BLOB);
CREATE TABLE cloud (id INTEGER PRIMARY KEY CHECK (id = 1), points BLOB NOT NULL, colors BLOB);
CREATE TABLE grasps (name TEXT PRIMARY KEY, T_obj_grasp BLOB NOT NULL);
"""


# ------------------------------------------------------------------------------------------ helpers
P = ParamSpec("P")
R = TypeVar("R")


def _decodes(method: Callable[Concatenate[TemplateDB, P], R]) -> Callable[Concatenate[TemplateDB, P], R]:
    """TemplateDB reads: a stored value that does not decode is a corrupt database, an InputError naming it."""
    @functools.wraps(method)
    def wrapper(self: TemplateDB, *args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return method(self, *args, **kwargs)
        except TooLarge as e:
            raise InputError(self.path, str(e)) from None
        except BadBlob as e:
            raise InputError(self.path, f"corrupt template database ({e})") from None
    return wrapper


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return (pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


# ----------------------------------------------------------------------------------------- database
def unregistered_names(views: list[View], skipped: Any) -> list[str]:
    """The frames a scan could not register, as `scan --json` lists them: the views without a pose (in
    order), then the input frames it could not read (the "skipped" meta, {name: reason}), each once."""
    unreg = [v.name for v in views if v.T_obj_cam is None]
    known = set(unreg)
    return unreg + sorted(n for n in (skipped if isinstance(skipped, dict) else {}) if n not in known)


def unregistered_reasons(names: list[str], reasons: Any, skipped: Any) -> dict[str, str]:
    """Why each of `names` has no pose: the scan's "unregistered_reasons" meta, else why it could not be read
    (its "skipped" meta); a name neither explains (a template written before reasons were kept) reads
    "not registered"."""
    known = {**(skipped if isinstance(skipped, dict) else {}), **(reasons if isinstance(reasons, dict) else {})}
    return {n: str(known.get(n, "not registered")) for n in names}


def selection_summary(meta: Any) -> dict:
    """A scan's frame selection as `scan --json` and `info` report it, from its "selection" meta: {"kept": int,
    "skipped": int, "reasons": {why: frames}}; {} when the template has none (written before frames were
    selected, or from a mesh)."""
    if not isinstance(meta, dict):
        return {}
    reasons = meta.get("reasons")
    return {"kept": int(meta.get("kept", 0)), "skipped": int(meta.get("skipped", 0)),
            "reasons": {str(k): int(v) for k, v in reasons.items()} if isinstance(reasons, dict) else {}}


def _journal_held_read_only(path: Path, e: BaseException) -> InputError | None:
    """The InputError for a database SQLite cannot open because a journal (or write-ahead log) left beside it by
    a writer that stopped must be rolled back into it, and the folder or the file cannot be written: the file is
    not corrupt, only held. None when no journal is there or the error is not a write refused."""
    if not isinstance(e, sqlite3.OperationalError):
        return None
    journals = [Path(f"{path}{x}") for x in SQLITE_SIDECARS if Path(f"{path}{x}").is_file()]
    if not journals:
        return None
    folder = path.parent.absolute()
    if not os.access(folder, os.W_OK):
        where = f"the folder {folder} is read-only"
    elif not os.access(path, os.W_OK):
        where = "the file is read-only"
    elif "readonly" in str(e).lower():
        where = "the folder or the file is read-only"
    else:
        return None
    return InputError(path, f"cannot be opened here: SQLite's journal {journals[0].name} beside it (left by a "
                      f"writer that stopped) must be rolled back into it, and {where}; the template is not "
                      "corrupt: open it once where it can be written (or copy it with the journal elsewhere)")


class TemplateDB:
    """A template database file. Use `create` or `open`, never the constructor; close it (or use `with`).

    Thread-safe (one lock around the connection), so the viewer may read it from a server thread.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, writable: bool, wal: bool = False):
        self.path = path
        self._conn: sqlite3.Connection | None = conn
        self._writable = writable
        self._wal = wal and writable and str(conn.execute("PRAGMA journal_mode").fetchone()[0]).lower() == "wal"
        self._lock = threading.RLock()
        self._batch = False  # a batch() transaction is open

    # -- opening ---------------------------------------------------------------------------------
    @staticmethod
    def _connect(path: Path, writable: bool = True, wal: bool = False) -> sqlite3.Connection:
        """A connection; a writer sets the journal (WAL with synchronous=NORMAL, else a rollback journal with
        synchronous=FULL), a reader keeps the file's (changing it needs every other connection gone: a reader of
        a scan under way would wait for it)."""
        conn = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False, timeout=30.0)
        if writable:
            mode = "delete"
            if wal:  # not every file system gives SQLite the shared memory a log needs: then a journal
                with suppress(sqlite3.OperationalError):
                    mode = str(conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]).lower()
            if mode != "wal":
                conn.execute("PRAGMA journal_mode=DELETE")
            conn.execute(f"PRAGMA synchronous={'NORMAL' if mode == 'wal' else 'FULL'}")
        return conn

    @classmethod
    def create(cls, path: str | Path, force: bool = False, meta: dict | None = None,
               wal: bool = False) -> TemplateDB:
        """Create a new database at `path` with status "partial".

        An existing `path` is refused (OutputExists) unless `force`, which replaces it; without `force`
        the file is created only if nothing is there at that moment (a concurrent creator is refused).
        `meta` adds meta keys (e.g. "source": "scan"|"mesh", "descriptor": {"kind": ...}, "config": {...}).
        `wal`: write through a write-ahead log (a writer of many records; see the module docstring).
        """
        path = Path(path)
        # the schema is written to a temporary sibling and put in place at once, so a crash never leaves
        # an empty or schema-less file at `path` (an existing one is replaced atomically)
        base = {"schema": SCHEMA_VERSION, "status": "partial", "units": "m", "source": "scan"}
        base.update(meta or {})
        base["schema"], base["status"] = SCHEMA_VERSION, "partial"
        out = Output(path, force=force, kind=".gscan file path")
        try:
            tmp = out.open()
            setup = cls(tmp, cls._connect(tmp), writable=True)
            try:
                with setup._tx() as c:
                    c.execute(f"PRAGMA application_id={APPLICATION_ID}")
                    c.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
                    for stmt in _SCHEMA.strip().split(";"):
                        if stmt.strip():
                            c.execute(stmt)
                    c.executemany("INSERT INTO meta(key, value) VALUES (?, ?)",
                                  [(k, json.dumps(v, sort_keys=True)) for k, v in base.items()])
            finally:
                setup.close()
            remove_sqlite_sidecars(path)  # a stale journal or log must not meet the new file
            created = file_identity(tmp)
            out.commit()
        except BaseException as e:
            out.discard()
            if isinstance(e, sqlite3.Error):  # a folder that cannot be written
                raise InputError(path, f"cannot create the database ({e})") from None
            t = out.translate(e)
            if t is not e:
                raise t from None
            raise
        db = cls(path, cls._connect(path, wal=wal), writable=True, wal=wal)
        if file_identity(path) != created:  # replaced by another writer between the rename and the connection
            db.close()
            raise InputError(path, "was replaced by another process while this one created it")
        log.info("created template database %s", path)
        return db

    @classmethod
    def open(cls, path: str | Path, require_complete: bool = True, writable: bool = False,
             wal: bool = False) -> TemplateDB:
        """Open an existing database. InputError (one line naming the file) when the file is missing,
        not SQLite, not a gscan database, of an unsupported schema, or partial while `require_complete`.
        `wal` (with `writable`): write through a write-ahead log, as `create`."""
        path = Path(path)
        if not path.is_file():
            raise not_a_file(path, "template database")
        try:
            with open(path, "rb") as f:
                head = f.read(len(_SQLITE_MAGIC))
        except OSError as e:
            raise InputError(path, f"cannot read template database ({e.__class__.__name__})") from None
        if head != _SQLITE_MAGIC:
            raise InputError(path, "not a gscan template database (not an SQLite file)")
        conn = None
        try:
            conn = cls._connect(path, writable=writable, wal=wal and writable)
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            has_meta = conn.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'").fetchone()
            if app_id != APPLICATION_ID or not has_meta:
                raise InputError(path, "not a gscan template database (an SQLite file of another application)")
            row = conn.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
            schema = json.loads(row[0]) if row else None
            row = conn.execute("SELECT value FROM meta WHERE key='status'").fetchone()
            status = json.loads(row[0]) if row else None
        except (sqlite3.DatabaseError, ValueError, RecursionError) as e:
            if conn is not None:
                conn.close()
            held = _journal_held_read_only(path, e)
            if held is not None:
                raise held from None
            raise InputError(path, f"corrupt or unreadable template database ({e.__class__.__name__}: {e})"[:300]
                             ) from None
        except InputError:
            if conn is not None:
                conn.close()
            raise
        if not isinstance(schema, int) or schema < 1:
            conn.close()
            raise InputError(path, f"unsupported old template schema {schema!r}; rebuild it with gscan scan")
        if schema > SCHEMA_VERSION:
            conn.close()
            raise InputError(path, f"written by a newer gscan (schema {schema}, this gscan reads {SCHEMA_VERSION}); "
                                   "upgrade gscan")
        if require_complete and status != "complete":
            conn.close()
            raise InputError(path, "is a partial scan (interrupted before it completed)", fix="finish")
        return cls(path, conn, writable, wal=wal and writable)

    def close(self) -> None:
        """Close the connection; a WAL writer first moves the log into the file and returns it to a rollback
        journal (left in WAL mode while another connection holds the file: still valid, its log goes at its
        last close)."""
        with self._lock:
            if self._conn is not None:
                if self._wal:
                    with suppress(sqlite3.Error):
                        self._conn.execute("PRAGMA journal_mode=DELETE")
                self._conn.close()
                self._conn = None

    def __enter__(self) -> TemplateDB:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, rolled back on any exception); inside a `batch`
        a savepoint of its transaction, so a write that fails leaves none of its rows in the batch."""
        if not self._writable:
            raise GscanError(f"{self.path}: opened read-only")
        with self._lock:
            c = self._live()
            begin, commit, rollback = (("SAVEPOINT w", "RELEASE w", "ROLLBACK TO w") if self._batch else
                                       ("BEGIN IMMEDIATE", "COMMIT", "ROLLBACK"))
            try:
                c.execute(begin)
                try:
                    yield c
                except BaseException:
                    with suppress(sqlite3.Error):
                        c.execute(rollback)
                        if self._batch:
                            c.execute(commit)
                    raise
                c.execute(commit)
            except sqlite3.DatabaseError as e:
                if isinstance(e, sqlite3.IntegrityError):
                    raise
                raise self._corrupt(e) from None

    def _live(self) -> sqlite3.Connection:
        if self._conn is None:
            raise GscanError(f"{self.path}: the template database is closed")
        return self._conn
    @contextmanager
    def batch(self) -> Iterator[None]:
        """The writes inside are one transaction, committed at the end (or at each `commit()` inside), rolled
        back on an exception: one commit for many records. Other threads may read meanwhile (they see the batch's
        rows); only the thread that opened the batch writes. Not nested."""
        if not self._writable:
            raise GscanError(f"{self.path}: opened read-only")
        with self._lock:
            if self._batch:
                raise GscanError(f"{self.path}: a batch is open already")
            self._execute("BEGIN IMMEDIATE")
            self._batch = True
        try:
            yield
        except BaseException:
            with self._lock:
                self._batch = False
                with suppress(sqlite3.Error):
                    self._live().execute("ROLLBACK")
            raise
        with self._lock:
            self._batch = False
            self._execute("COMMIT")

    def commit(self) -> None:
        """Inside a `batch`: commit what it wrote so far and go on in a new transaction (a long stage commits
        in chunks, so a crash loses at most the last one); outside one, nothing to do."""
        with self._lock:
            if self._batch:
                self._execute("COMMIT")
                self._execute("BEGIN IMMEDIATE")

    def _execute(self, sql: str) -> None:
        try:
            self._live().execute(sql)
        except sqlite3.DatabaseError as e:
            raise self._corrupt(e) from None

    def _q(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._live().execute(sql, args).fetchall()
            except sqlite3.DatabaseError as e:
                raise self._corrupt(e) from None

    def _corrupt(self, e: sqlite3.DatabaseError) -> InputError:
        """An error SQLite reports while reading or writing pages (past open()'s checks), named for what it
        is: a full disk or the file size limit, a read-only file, a file replaced meanwhile, a lock held
        too long, or else corruption. Bad input naming the database, not an internal error."""
        code = getattr(e, "sqlite_errorcode", None)
        primary = None if code is None else code & 0xFF
        if primary == _SQLITE_FULL:
            return InputError(self.path, "cannot write the template database: no space left on the device (disk full)")
        if primary == _SQLITE_IOERR:
            why = write_failure_reason(self.path) or f"an I/O error ({e})"
            return InputError(self.path, f"cannot write the template database: {why}")
        if code == _SQLITE_READONLY_DBMOVED:
            return InputError(self.path, "cannot write the template database: the file was moved or replaced "
                              "(by another process) while this one wrote it")
        if primary == _SQLITE_READONLY or "readonly" in str(e):
            return InputError(self.path, "cannot write the template database (a read-only file or folder)")
        if primary in (_SQLITE_BUSY, _SQLITE_LOCKED):
            return InputError(self.path, "the template database is locked by another process (waited 30 s)")
        if primary == _SQLITE_CANTOPEN:
            return InputError(self.path, f"cannot open the template database or its journal beside it ({e})")
        return InputError(self.path, f"corrupt template database ({e.__class__.__name__}: {e})")

    # -- meta ------------------------------------------------------------------------------------
    @_decodes
    def get_meta(self, key: str, default: Any = None) -> Any:
        rows = self._q("SELECT value FROM meta WHERE key=?", (key,))
        return decode_json(rows[0][0]) if rows else default

    def set_meta(self, key: str, value: Any) -> None:
        """Set one meta key to a JSON-serialisable value ("schema" is not settable)."""
        if key == "schema":
            raise ValueError("the schema version is fixed at creation")
        with self._tx() as c:
            c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)", (key, json.dumps(value, sort_keys=True)))

    @_decodes
    def meta(self) -> dict:
        return {k: decode_json(v) for k, v in self._q("SELECT key, value FROM meta ORDER BY key")}

    @property
    def status(self) -> str:
        return self.get_meta("status", "partial")

    def mark_complete(self) -> None:
        self.set_meta("status", "complete")

    def mark_partial(self) -> None:
        """Back to "partial" (a resumed scan calls this before writing)."""
        self.set_meta("status", "partial")

    # -- views -----------------------------------------------------------------------------------
    def add_view(self, view: View, features: Features | None = None, color_codec: str = "jpg",
                 replace: bool = False) -> int:
        """Store a view (and optionally its keypoints) in one transaction; returns its id.

        color_codec: "jpg" (quality 90) or "png" (lossless). An existing name is an error unless
        `replace` (which also drops the old view's keypoints).
        """
        if color_codec not in ("jpg", "png"):
            raise ValueError(f"color_codec must be 'jpg' or 'png', not {color_codec!r}")
        T = check_T(view.T_obj_cam)
        row = (view.name, view.input_index, json.dumps(view.intrinsics.to_dict(), sort_keys=True), encode_array(T),
               None if view.color is None else encode_color(view.color, color_codec),
               None if view.color is None else color_codec,
               None if view.depth is None else encode_depth(view.depth),
               None if view.mask is None else encode_mask(view.mask),
               int(bool(view.keyframe)), None if view.quality is None else float(view.quality))
        with self._tx() as c:
            old = c.execute("SELECT id FROM views WHERE name=?", (view.name,)).fetchone()
            if old is not None:
                if not replace:
                    raise InputError(self.path, f"view {view.name!r} already exists")
                c.execute("DELETE FROM features WHERE view_id=?", (old[0],))
                c.execute("DELETE FROM views WHERE id=?", (old[0],))
            vid = c.execute("INSERT INTO views(name, input_index, intrinsics, T_obj_cam, color, color_codec, depth, "
                            "mask, keyframe, quality) VALUES (?,?,?,?,?,?,?,?,?,?)", row).lastrowid
            assert vid is not None  # the id of the row just inserted
            if features is not None:
                self._put_features(c, vid, features)
        return int(vid)

    @_decodes
    def _view_id(self, c: sqlite3.Connection, name: str) -> tuple[int, np.ndarray | None]:
        row = c.execute("SELECT id, T_obj_cam FROM views WHERE name=?", (name,)).fetchone()
        if row is None:
            raise KeyError(f"no view named {name!r} in {self.path}")
        return int(row[0]), decode_T(row[1])

    @_decodes
    def update_pose(self, name: str, T_obj_cam: np.ndarray | None, move_features: bool = True) -> None:
        """Set (or clear, None) a view's pose. With `move_features` its stored keypoint points are
        re-expressed: p_new = T_new @ inv(T_old) @ p_old (identity stands for a missing pose)."""
        T_new = check_T(T_obj_cam)
        with self._tx() as c:
            self._set_pose(c, name, T_new, move_features)

    @_decodes
    def update_view(self, name: str, *, T_obj_cam: np.ndarray | None, mask: np.ndarray | None, keyframe: bool,
                    quality: float | None) -> None:
        """Set a stored view's pose (its keypoints re-expressed, as `update_pose`), mask [H x W] bool (None: none),
        keyframe flag and quality, in one transaction; its images stay as stored (a scan writes them once)."""
        T_new = check_T(T_obj_cam)
        m = None if mask is None else encode_mask(mask)
        with self._tx() as c:
            vid = self._set_pose(c, name, T_new, True)
            c.execute("UPDATE views SET mask=?, keyframe=?, quality=? WHERE id=?",
                      (m, int(bool(keyframe)), None if quality is None else float(quality), vid))

    def _set_pose(self, c: sqlite3.Connection, name: str, T_new: np.ndarray | None, move_features: bool) -> int:
        vid, T_old = self._view_id(c, name)
        c.execute("UPDATE views SET T_obj_cam=? WHERE id=?", (encode_array(T_new), vid))
        A = (np.eye(4) if T_new is None else T_new) @ np.linalg.inv(np.eye(4) if T_old is None else T_old)
        if T_old is None and T_new is not None:
            A = T_new  # camera frame to object frame: the points exactly as Features.transformed maps them
        if T_old is None and T_new is None:
            move_features = False  # still in the camera frame
        rows = c.execute("SELECT role, points FROM features WHERE view_id=?", (vid,)).fetchall()
        for role, pts in rows if move_features else []:
            c.execute("UPDATE features SET points=? WHERE view_id=? AND role=?",
                      (encode_array(_apply(A, decode_array(pts, (None, 3)))), vid, role))
        return vid

    def remove_view(self, name: str) -> None:
        """Remove a view, its keypoints and the edges that join it to other views (nothing when there is none)."""
        with self._tx() as c:
            row = c.execute("SELECT id FROM views WHERE name=?", (name,)).fetchone()
            if row is not None:
                c.execute("DELETE FROM features WHERE view_id=?", (row[0],))
                c.execute("DELETE FROM views WHERE id=?", (row[0],))
            c.execute("DELETE FROM edges WHERE src=? OR tgt=?", (name, name))

    def rename_views(self, prefix: str) -> None:
        """Put `prefix` before the name of every view, in the views and in the edges that join them (a template
        of one capture becoming one of several: its frames named `CAPTURE/FRAME`)."""
        with self._tx() as c:
            c.execute("UPDATE views SET name = ? || name", (prefix,))
            c.execute("UPDATE edges SET src = ? || src, tgt = ? || tgt", (prefix, prefix))

    def view_names(self) -> list[str]:
        """All view names in input order (input_index, then insertion)."""
        return [r[0] for r in self._q("SELECT name FROM views ORDER BY input_index IS NULL, input_index, id")]

    @_decodes
    def _row_to_view(self, r: tuple, load_images: bool) -> View:
        name, idx, intr, T, color, _codec, depth, mask, kf, q = r
        try:
            K = Intrinsics.from_dict(decode_json(intr))
        except (KeyError, TypeError, ValueError) as e:
            raise BadBlob(f"view {name!r}: bad intrinsics {e}") from None
        too_large = image_too_large(K.width, K.height)  # what the view's images and rays would take
        if too_large:
            raise TooLarge(f"view {name!r}: its intrinsics are for images of {K.width}x{K.height}: {too_large}")
        v = View(name=name, intrinsics=K, T_obj_cam=decode_T(T), keyframe=bool(kf),
                 quality=q, input_index=idx)
        if load_images:
            wh = (K.width, K.height)
            v.color = (None if color is None
                       else np.ascontiguousarray(cv2.cvtColor(decode_image(color, np.uint8, 3, wh), cv2.COLOR_BGR2RGB)))
            v.depth = (None if depth is None
                       else decode_image(depth, np.uint16, 1, wh).astype(np.float32) / np.float32(1000.0))
            v.mask = None if mask is None else decode_image(mask, np.uint8, 1, wh) > 127
        return v

    _VIEW_COLS = "name, input_index, intrinsics, T_obj_cam, {img}, color_codec, {img2}, {img3}, keyframe, quality"

    def _view_sql(self, load_images: bool) -> str:
        cols = self._VIEW_COLS.format(img="color" if load_images else "NULL", img2="depth" if load_images else "NULL",
                                      img3="mask" if load_images else "NULL")
        return f"SELECT {cols} FROM views"

    def views(self, load_images: bool = False, keyframes_only: bool = False) -> list[View]:
        """All views in input order; images decoded only with `load_images`."""
        where = " WHERE keyframe=1" if keyframes_only else ""
        rows = self._q(self._view_sql(load_images) + where + " ORDER BY input_index IS NULL, input_index, id")
        return [self._row_to_view(r, load_images) for r in rows]

    def view(self, name: str, load_images: bool = True) -> View:
        rows = self._q(self._view_sql(load_images) + " WHERE name=?", (name,))
        if not rows:
            raise KeyError(f"no view named {name!r} in {self.path}")
        return self._row_to_view(rows[0], load_images)

    # -- features --------------------------------------------------------------------------------
    def _put_features(self, c: sqlite3.Connection, vid: int, f: Features, role: str = "registration") -> None:
        if role not in FEATURE_ROLES:
            raise ValueError(f"feature role must be one of {FEATURE_ROLES}, not {role!r}")
        px = np.asarray(f.pixels, dtype=np.float32).reshape(-1, 2)
        pts = np.asarray(f.points, dtype=np.float32).reshape(-1, 3)
        desc = np.asarray(f.descriptors)
        if desc.ndim != 2:
            desc = desc.reshape(len(px), -1) if len(px) else desc.reshape(0, 0)
        sc = None if f.scales is None else np.asarray(f.scales, dtype=np.float32).reshape(-1)
        if len(pts) != len(px) or len(desc) != len(px) or (sc is not None and len(sc) != len(px)):
            raise ValueError(f"keypoint arrays disagree: {len(px)} pixels, {len(pts)} points, {len(desc)} descriptors")
        c.execute("INSERT OR REPLACE INTO features(view_id, role, kind, n, pixels, points, descriptors, scales) "
                  "VALUES (?,?,?,?,?,?,?,?)",
                  (vid, role, str(f.kind), len(px), encode_array(px), encode_array(pts), encode_array(desc),
                   encode_array(sc)))

    def add_features(self, view_name: str, features: Features, role: str = "registration") -> None:
        """Store (replace) a view's keypoints of a role (FEATURE_ROLES); their points in the object frame, in
        the camera frame while the view is unregistered."""
        f = features
        with self._tx() as c:
            vid, _ = self._view_id(c, view_name)
            self._put_features(c, vid, f, role)

    @_decodes
    def features(self, view_name: str, role: str = "registration") -> Features | None:
        """The view's keypoints of a role (points in the object frame; camera frame for an unregistered view);
        None if it has none."""
        rows = self._q("SELECT f.pixels, f.points, f.descriptors, f.kind, f.scales, f.n FROM features f "
                       "JOIN views v ON v.id = f.view_id WHERE v.name=? AND f.role=?", (view_name, role))
        if not rows:
            return None
        px, pts, desc, kind, sc, n = rows[0]
        n = n if isinstance(n, int) and n >= 0 else -1  # the stored count: every array must hold that many
        px, pts, desc, sc = (decode_array(px, (n, 2)), decode_array(pts, (n, 3)), decode_array(desc, (n, None)),
                             decode_array(sc, (n,)))
        check_keypoints(px, pts, desc, sc, kind, f"view {view_name!r}")
        return Features(pixels=px, points=pts, descriptors=desc, kind=kind, scales=sc)

    # -- edges -----------------------------------------------------------------------------------
    def add_edge(self, edge: Edge) -> None:
        """Store (replace) the edge src -> tgt."""
        if edge.kind not in ("sequential", "loop"):
            raise ValueError(f"edge kind must be 'sequential' or 'loop', not {edge.kind!r}")
        m = np.asarray(edge.matches, dtype=np.int32).reshape(-1, 2)

        def f(x: float | None) -> float | None:
            return None if x is None else float(x)

        with self._tx() as c:
            c.execute("DELETE FROM edges WHERE src=? AND tgt=?", (edge.src, edge.tgt))
            c.execute("INSERT INTO edges(src, tgt, T_tgt_src, matches, cost, rmse, fitness, kind, accepted, reason) "
                      "VALUES (?,?,?,?,?,?,?,?,?,?)",
                      (edge.src, edge.tgt, encode_array(check_T(edge.T_tgt_src)), encode_array(m), f(edge.cost),
                       f(edge.rmse), f(edge.fitness), edge.kind, int(bool(edge.accepted)), edge.reason))

    @_decodes
    def edges(self, accepted_only: bool = False) -> list[Edge]:
        where = " WHERE accepted=1" if accepted_only else ""
        rows = self._q("SELECT src, tgt, T_tgt_src, matches, cost, rmse, fitness, kind, accepted, reason FROM edges"
                       + where + " ORDER BY id")
        return [Edge(src=s, tgt=t, T_tgt_src=decode_T(T), matches=decode_array(m, (None, 2)), cost=co, rmse=r,
                     fitness=fi, kind=k, accepted=bool(a), reason=re)
                for s, t, T, m, co, r, fi, k, a, re in rows]

    # -- geometry and grasps ---------------------------------------------------------------------
    def set_mesh(self, mesh: MeshData) -> None:
        """Store (replace) the mesh: vertices [V x 3] (m, object frame), triangles [F x 3], vertex colours
        [V x 3] uint8 or float in [0, 1] (stored as uint8)."""
        V = np.asarray(mesh.vertices).reshape(-1, 3)
        F = np.asarray(mesh.triangles).reshape(-1, 3)
        C = to_u8_colors(mesh.vertex_colors)
        if C is not None and len(C) != len(V):
            raise ValueError(f"{len(C)} vertex colours for {len(V)} vertices")
        with self._tx() as c:
            c.execute("INSERT OR REPLACE INTO mesh(id, vertices, triangles, colors) VALUES (1,?,?,?)",
                      (encode_array(V), encode_array(F), encode_array(C)))

    @_decodes
    def mesh(self) -> MeshData | None:
        rows = self._q("SELECT vertices, triangles, colors FROM mesh WHERE id=1")
        if not rows:
            return None
        V, F, C = (decode_array(b, (None, 3)) for b in rows[0])
        check_mesh(V, F, C)
        return MeshData(vertices=V, triangles=F, vertex_colors=C)

    def set_cloud(self, points: np.ndarray, colors: np.ndarray | None = None) -> None:
        """points [N x 3] (m, object frame), colors [N x 3] uint8 or float in [0, 1]."""
        P = np.asarray(points).reshape(-1, 3)
        C = to_u8_colors(colors)
        if C is not None and len(C) != len(P):
            raise ValueError(f"{len(C)} colours for {len(P)} points")
        with self._tx() as c:
            c.execute("INSERT OR REPLACE INTO cloud(id, points, colors) VALUES (1,?,?)",
                      (encode_array(P), encode_array(C)))

    @_decodes
    def cloud(self) -> tuple[np.ndarray, np.ndarray | None] | None:
        rows = self._q("SELECT points, colors FROM cloud WHERE id=1")
        if not rows:
            return None
        P, C = decode_array(rows[0][0], (None, 3)), decode_array(rows[0][1], (None, 3))
        check_colors(C, len(P), "cloud")
        return P, C

    def add_grasp(self, name: str, T_obj_grasp: np.ndarray, replace: bool = False) -> None:
        T = check_T(T_obj_grasp)
        if not is_rigid(T):
            raise ValueError("a grasp pose must be a rigid transform within 10 km")
        try:
            name.encode("utf-8")
        except UnicodeEncodeError:
            raise InputError(self.path, f"grasp name {name!r} is not UTF-8 text") from None
        if not name.strip() or not name.isprintable() or len(name) > 200:
            raise InputError(self.path, f"grasp name {name[:40]!r} must be 1-200 printable characters")
        with self._tx() as c:
            if not replace and c.execute("SELECT 1 FROM grasps WHERE name=?", (name,)).fetchone():
                raise InputError(self.path, f"grasp {name!r} already exists")
            c.execute("INSERT OR REPLACE INTO grasps(name, T_obj_grasp) VALUES (?,?)", (name, encode_array(T)))

    @_decodes
    def grasps(self) -> dict[str, np.ndarray]:
        return {n: decode_T(b) for n, b in self._q("SELECT name, T_obj_grasp FROM grasps ORDER BY name")}

    # -- summaries -------------------------------------------------------------------------------
    def descriptor_kind(self) -> str | None:
        d = self.get_meta("descriptor")
        if isinstance(d, dict) and "kind" in d:
            return str(d["kind"])
        if isinstance(d, str):
            return d
        rows = self._q("SELECT kind FROM features ORDER BY view_id LIMIT 1")
        return rows[0][0] if rows else None

    @_decodes
    def extent(self) -> np.ndarray:
        """[3] axis-aligned size (m) in the object frame of the mesh, else the cloud, else the keypoints."""
        m = self.mesh()
        pts = m.vertices if m is not None and len(m.vertices) else None
        if pts is None:
            cl = self.cloud()
            pts = cl[0] if cl is not None and len(cl[0]) else None
        if pts is None:
            rows = self._q("SELECT f.points FROM features f JOIN views v ON v.id=f.view_id "
                           "WHERE v.T_obj_cam IS NOT NULL AND f.n > 0")
            pts = np.concatenate([decode_array(r[0], (None, 3)) for r in rows]) if rows else None
        if pts is None or len(pts) == 0:
            return np.zeros(3)
        pts = np.asarray(pts, dtype=np.float64)
        return pts.max(axis=0) - pts.min(axis=0)

    def summary(self) -> TemplateSummary:
        """What the database holds (works on a partial one too)."""
        n_views, n_reg, n_kf = self._q("SELECT COUNT(*), COUNT(T_obj_cam), COALESCE(SUM(keyframe), 0) FROM views")[0]
        x, y, z = (float(v) for v in self.extent())
        unreg = unregistered_names(self.views(), self.get_meta("skipped"))
        return TemplateSummary(schema=int(self.get_meta("schema")), status=self.status, views=int(n_views),
                               registered=int(n_reg), keyframes=int(n_kf), descriptor=self.descriptor_kind(),
                               source=self.get_meta("source", "scan"), extent_m=(x, y, z),
                               grasps=tuple(sorted(self.grasps())),
                               unregistered_reasons=unregistered_reasons(unreg, self.get_meta("unregistered_reasons"),
                                                                         self.get_meta("skipped")),
                               selection=selection_summary(self.get_meta("selection")), parts=self.parts())

    def coverage(self) -> CoverageMap | None:
        """Which viewing directions of the object the template has seen (`gscan.geometry.coverage`; its "coverage"
        meta, written by the scan and by template-from-mesh); None for a template made before it was recorded.
        InputError naming the database when the stored map is malformed."""
        meta = self.get_meta("coverage")
        if meta is None:
            return None
        try:
            return CoverageMap.from_meta(meta)
        except ValueError as e:
            raise InputError(self.path, f"malformed coverage record: {e}") from None
    def symmetries(self) -> Symmetries:
        """The object's symmetries (its "symmetries" meta, `Symmetries.to_json`'s form; none when absent, as in
        templates written before symmetries were found). InputError naming the database for a malformed one."""
        try:
            return Symmetries.from_json(self.get_meta("symmetries"))
        except ValueError as e:
            raise InputError(self.path, f"meta 'symmetries': {e}") from None

    def parts(self) -> list[list[str]]:
        """The frames of each part of the capture that no confident edge joins to the template's frames (largest
        first; the scan's "parts" meta, empty when there is none or the scan predates it)."""
        parts = self.get_meta("parts")
        return [[str(n) for n in p] for p in parts if isinstance(p, list)] if isinstance(parts, list) else []

    def poses(self) -> dict:
        """The dict `gscan poses --json` prints: {"frames": {name: T_obj_cam}, "unregistered": [names],
        "unregistered_reasons": {name: reason}, "skipped_by_selection": {name: reason}, "from_reference":
        {name: kept frame}, "parts": [[names]]}; frames skipped by selection that were placed by registration to the
        kept frame they were compared with (`from_reference`) are in "frames" too;
        unregistered as in `scan --json`: the views without a pose, then the input frames the scan could not read
        (its "skipped" meta); skipped by selection: the input frames the scan's frame selection left out (not
        failures); parts: `parts()`."""
        views = self.views()
        frames = {v.name: v.T_obj_cam.tolist() for v in views if v.T_obj_cam is not None}
        unreg = unregistered_names(views, self.get_meta("skipped"))
        sel = self.get_meta("selection")
        skipped = sel.get("frames") if isinstance(sel, dict) else None
        skipped = {str(k): str(v) for k, v in skipped.items()} if isinstance(skipped, dict) else {}
        placed = self.get_meta("selection_poses")
        placed = placed if isinstance(placed, dict) else {}
        frames |= {str(k): v for k, v in (placed.get("frames") or {}).items() if str(k) in skipped}
        for k, why in (placed.get("reasons") or {}).items():  # not placed: why, after why it was skipped
            if str(k) in skipped:
                skipped[str(k)] = f"{skipped[str(k)]}; {why}"
        return {"frames": frames, "unregistered": unreg,
                "unregistered_reasons": unregistered_reasons(unreg, self.get_meta("unregistered_reasons"),
                                                             self.get_meta("skipped")),
                "skipped_by_selection": skipped,
                "from_reference": {str(k): str(v) for k, v in (placed.get("reference") or {}).items()
                                   if str(k) in frames},
                "parts": self.parts()}

    def load_template(self, keyframes_only: bool = True) -> Template:
        """Everything the estimator needs, loaded once: registered (key)frame views with their keypoints
        (a view's "object" keypoints where they were stored, else its "registration" keypoints)."""
        views = [v for v in self.views(keyframes_only=keyframes_only) if v.T_obj_cam is not None]
        names, intr, Ts, px, pts, desc, kv, offs = [], [], [], [], [], [], [], [0]
        kind = self.descriptor_kind()
        for v in views:
            f = self.features(v.name, "object")
            if f is None:  # no object keypoints stored (an unsegmented scan): the view's own; an empty set stays empty
                f = self.features(v.name)
            names.append(v.name)
            intr.append(v.intrinsics)
            Ts.append(v.T_obj_cam)
            if f is not None and len(f.pixels):
                px.append(f.pixels)
                pts.append(f.points)
                desc.append(f.descriptors)
                kv.append(np.full(len(f.pixels), len(names) - 1, dtype=np.int32))
                kind = kind or f.kind
            offs.append(offs[-1] + (0 if f is None else len(f.pixels)))
        ddtype = np.uint8 if kind == "orb" else np.float32
        cl = self.cloud()
        return Template(
            path=self.path, meta=self.meta(), kind=kind, view_names=names, intrinsics=intr,
            T_obj_cam=np.array(Ts, dtype=np.float64).reshape(-1, 4, 4),
            kp_view=np.concatenate(kv) if kv else np.zeros(0, np.int32),
            pixels=np.concatenate(px) if px else np.zeros((0, 2), np.float32),
            points_obj=np.concatenate(pts) if pts else np.zeros((0, 3), np.float32),
            descriptors=np.concatenate(desc) if desc else np.zeros((0, 0), ddtype),
            view_offsets=np.array(offs, dtype=np.int64),
            cloud_points=None if cl is None else cl[0], cloud_colors=None if cl is None else cl[1],
            mesh=self.mesh(), grasps=self.grasps(), extent_m=self.extent())


def open_template(path: str | Path) -> Template:
    """Open a complete database and load its Template (InputError as `TemplateDB.open`)."""
    with TemplateDB.open(path, require_complete=True) as db:
        return db.load_template()


def open_estimable(path: str | Path) -> Template:
    """`open_template`, refused (InputError) unless the template holds a registered view with keypoints (what an
    estimate needs): the callers check a template this way before the estimator's stages (numba, scipy) load."""
    template = open_template(path)
    template.require_keypoints()
    return template
