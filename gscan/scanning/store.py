"""The kept frames' images while a scan runs, on disk: what the later stages reload on demand instead of holding
every frame in memory.

`FrameStore` appends each frame's arrays (colour, depth, masks: exact, the template database's codecs are lossy)
to an anonymous temporary file in the output's folder: it has no name, so nothing of it outlives the process,
a killed one included, and it lives on the output's file system (a temporary folder may be memory). Reads are
positional and thread-safe. A write error (disk full, the file size limit) is an InputError naming the output.
"""
from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Generic, TypeVar, overload

import numpy as np

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self from Python 3.11

from gscan.io.camera import Intrinsics, RGBDFrame
from gscan.io.output import write_error


@dataclass(frozen=True)
class _Slot:
    offset: int
    dtype: str
    shape: tuple[int, ...]
    packed: bool  # a bool array stored with np.packbits


class FrameStore:
    """Arrays by (key, name), appended to an anonymous file beside `output` (see the module docstring)."""

    def __init__(self, output: Path):
        self.output = Path(output)
        folder = next(d for d in (self.output.absolute().parent, *self.output.absolute().parents) if d.is_dir())
        try:
            self._file = tempfile.TemporaryFile(dir=folder, prefix=".gscan-frames-")  # noqa: SIM115 - closed by close()
        except OSError as e:
            raise write_error(self.output, e) from None
        self._fd = self._file.fileno()
        self._end = 0
        self._slots: dict[tuple[str, str], _Slot] = {}
        self._lock = threading.Lock()

    def put(self, key: str, **arrays: np.ndarray | None) -> None:
        """Store arrays under `key` (a None array is not stored; storing a name again replaces it)."""
        for name, a in arrays.items():
            if a is None:
                continue
            a = np.ascontiguousarray(a)
            packed = a.dtype == np.bool_
            data = np.packbits(a, axis=None) if packed else a
            buf = data.reshape(-1).view(np.uint8).data
            with self._lock:
                offset = self._end
                self._end += len(buf)
            try:
                done = 0
                while done < len(buf):
                    done += os.pwrite(self._fd, buf[done:], offset + done)
            except OSError as e:
                raise write_error(self.output, e) from None
            with self._lock:
                self._slots[(key, name)] = _Slot(offset, a.dtype.str, a.shape, packed)

    def has(self, key: str, name: str) -> bool:
        return (key, name) in self._slots

    def need(self, key: str, name: str) -> np.ndarray:
        """`get` of an array that must be there (KeyError otherwise)."""
        a = self.get(key, name)
        if a is None:
            raise KeyError(f"{key}/{name} is not in the scan's frame store")
        return a

    def get(self, key: str, name: str) -> np.ndarray | None:
        """The array stored under (key, name), a new writable copy; None when there is none."""
        slot = self._slots.get((key, name))
        if slot is None:
            return None
        count = int(np.prod(slot.shape, dtype=np.int64))
        out = np.empty((count + 7) // 8 if slot.packed else count, dtype=np.uint8 if slot.packed else slot.dtype)
        view = out.view(np.uint8).data
        done = 0
        while done < len(view):
            got = os.preadv(self._fd, [view[done:]], slot.offset + done)
            if got <= 0:
                raise OSError(f"the scan's frame store ended early ({key}/{name})")
            done += got
        if slot.packed:
            return np.unpackbits(out, count=count).astype(bool).reshape(slot.shape)
        return out.reshape(slot.shape)

    @property
    def size(self) -> int:
        """Bytes written so far."""
        return self._end

    def close(self) -> None:
        """Close (and so remove) the file."""
        self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class StoredFrame:
    """What a scan keeps in memory of a kept frame whose images are in a `FrameStore`: its name, intrinsics and
    source, and whether it came with an object mask."""

    name: str
    intrinsics: Intrinsics
    source: Path | None
    has_mask: bool

    @classmethod
    def put(cls, store: FrameStore, frame: RGBDFrame) -> StoredFrame:
        store.put(frame.name, color=frame.color, depth=frame.depth, given_mask=frame.mask)
        return cls(frame.name, frame.intrinsics, frame.source, frame.mask is not None)

    def load(self, store: FrameStore) -> RGBDFrame:
        """The frame as it was read: [H x W x 3] uint8 colour, [H x W] float32 depth (m), its given mask."""
        return RGBDFrame(name=self.name, color=store.need(self.name, "color"), depth=store.need(self.name, "depth"),
                         intrinsics=self.intrinsics,
                         mask=store.get(self.name, "given_mask") if self.has_mask else None, source=self.source)


T = TypeVar("T")


class LazyList(Sequence[T], Generic[T]):
    """A read-only sequence of `n` items made on demand by `item(i)` (nothing is kept): frames read from a store
    where a stage takes a list."""

    def __init__(self, n: int, item: Callable[[int], T]):
        self._n, self._item = n, item

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> T: ...

    @overload
    def __getitem__(self, i: slice) -> list[T]: ...

    def __getitem__(self, i: int | slice) -> T | list[T]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._n))]
        if not -self._n <= i < self._n:
            raise IndexError(i)
        return self._item(i % self._n)
