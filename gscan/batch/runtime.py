"""Ray for the batch commands: the optional import, a local runtime or a cluster, and the attempt tracker.

Ray is an optional extra (`pip install 'gscan[ray]'`); `require_ray` names the install command when it is
missing. `ray_runtime(address, workers)` yields a connected `Runtime`:
- without an address, a local Ray runtime of its own (`address="local"`: never one another program started),
  sized to the machine (`workers` CPUs, default all the CPUs this process may use), without the dashboard or
  usage statistics, its logs kept out of the terminal, its session files under a temporary folder that is
  removed when it shuts down at the end; its workers import the same gscan as this process;
- with an address ("auto": the cluster started on this machine with `ray start --head`; "ray://HOST:PORT":
  Ray Client), that cluster, left running at the end. Every node must have gscan installed (the same version:
  each task checks) and see the captures and templates at the same paths (a shared file system).
A program that has already called `ray.init` keeps its own connection: the runtime is used as it is.

Each capture or evaluation is one task asking for one CPU (`TASK_CPUS`) and retried `MAX_RETRIES` times when
its worker process dies (Ray's `max_retries`); the task's heavy work runs in a child process with one BLAS /
OpenMP / numba thread (`gscan.batch.jobs`). `AttemptTracker`, an actor without a CPU, counts each task's
attempts and knows which are running, for the progress display and the report.
"""
from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from gscan.errors import GscanError, InputError

RAY_MIN_VERSION = (2, 9)
INSTALL_HINT = "pip install 'gscan[ray]'"
MAX_RETRIES = 2  # attempts after the first when a task's worker process dies (Ray's max_retries)
TASK_CPUS = 1
OBJECT_STORE_BYTES = 128 * 1024 * 1024  # results are small JSON rows: Ray's floor is 75 MiB
# a unix socket path (Ray's plasma store, in its session folder) must stay within 107 bytes
_MAX_TEMP_ROOT = 48



class RayMissing(GscanError):
    """Ray is not installed (or too old): the batch commands need it."""


def require_ray() -> ModuleType:
    """The `ray` module; RayMissing, with the install command, when it cannot be imported or is older than
    RAY_MIN_VERSION."""
    try:
        import ray
    except ImportError:
        raise RayMissing(f"the batch commands run on Ray, an optional extra that is not installed: {INSTALL_HINT}"
                         ) from None
    try:
        version = tuple(int(x) for x in ray.__version__.split(".")[:2])
    except (AttributeError, ValueError):
        version = RAY_MIN_VERSION
    if version < RAY_MIN_VERSION:
        need = ".".join(map(str, RAY_MIN_VERSION))
        raise RayMissing(f"the batch commands need Ray >= {need}, this is Ray {ray.__version__}: {INSTALL_HINT}")
    return ray


def machine_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def package_root() -> Path:
    """The folder holding the `gscan` package this module belongs to (what workers and children import)."""
    return Path(__file__).resolve().parents[2]


def with_package_path(env: dict[str, str]) -> dict[str, str]:
    """`env` with this gscan's folder first on PYTHONPATH (another gscan may be installed on the machine)."""
    root = str(package_root())
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p != root]
    return env | {"PYTHONPATH": os.pathsep.join([root, *rest])}


class AttemptTracker:
    """Counts the attempts of each task (a retried task starts again) and the running ones (key -> start)."""

    def __init__(self) -> None:
        self.attempts: dict[str, int] = {}
        self.running: dict[str, float] = {}

    def started(self, key: str) -> int:
        """Record that the task `key` starts an attempt; returns the attempt's number (1 for the first)."""
        self.attempts[key] = self.attempts.get(key, 0) + 1
        self.running[key] = time.monotonic()
        return self.attempts[key]

    def ended(self, key: str) -> None:
        self.running.pop(key, None)

    def snapshot(self) -> dict[str, Any]:
        """{"running": {key: seconds since its attempt started}, "attempts": {key: attempts}}."""
        now = time.monotonic()
        return {"running": {k: now - t for k, t in self.running.items()}, "attempts": dict(self.attempts)}


@dataclass
class Runtime:
    """A connected Ray runtime: the module, the tracker actor's handle, the CPUs it offers (its `capacity`:
    the local runtime's size, or the cluster's CPUs, at most `workers`), where it runs ("local" or the
    address) and the task's options."""

    ray: ModuleType
    tracker: Any
    capacity: int
    where: str
    limit: int | None  # at most this many tasks at once (--workers on a cluster); None: as many as Ray runs

    def remote(self, fn: Any) -> Any:
        """`fn` as a Ray task of one CPU, retried MAX_RETRIES times when its worker dies."""
        return self.ray.remote(num_cpus=TASK_CPUS, max_retries=MAX_RETRIES, retry_exceptions=False)(fn)


def _temp_root() -> str:
    base = tempfile.gettempdir()
    if len(base) > _MAX_TEMP_ROOT and os.path.isdir("/tmp"):
        base = "/tmp"
    return tempfile.mkdtemp(prefix="gscan-ray-", dir=base)


@contextlib.contextmanager
def _environ(changes: dict[str, str]) -> Iterator[None]:
    """os.environ with `changes` while the block runs (the local runtime's processes inherit them)."""
    old = {k: os.environ.get(k) for k in changes}
    os.environ.update(changes)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def ray_runtime(address: str | None = None, workers: int | None = None) -> Iterator[Runtime]:
    """A Ray runtime for the batch tasks (see the module docstring); shut down (local) or disconnected
    (cluster) at the end. InputError when the cluster at `address` cannot be reached."""
    ray = require_ray()
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, not {workers}")
    owned, temp = False, None
    if ray.is_initialized():
        where = "the caller's Ray runtime"
    elif address is None:
        temp = _temp_root()
        n = workers or machine_cpus()
        env = with_package_path(dict(os.environ)) | {"RAY_USAGE_STATS_ENABLED": "0"}
        try:
            with _environ({k: env[k] for k in ("PYTHONPATH", "RAY_USAGE_STATS_ENABLED")}):
                ray.init(address="local", num_cpus=n, include_dashboard=False, _temp_dir=temp,
                         logging_level=logging.ERROR, log_to_driver=False, object_store_memory=OBJECT_STORE_BYTES)
        except BaseException:
            shutil.rmtree(temp, ignore_errors=True)
            raise
        owned, where = True, "local"
    else:
        try:
            with _environ({"RAY_USAGE_STATS_ENABLED": "0"}):
                ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError, TimeoutError) as e:
            raise InputError(None, f"cannot connect to the Ray cluster at {address}: "
                             f"{' '.join(str(e).split())[:300]}") from None
        owned, where = True, address
    tracker = None
    try:
        cpus = int(ray.cluster_resources().get("CPU", 0))
        limit = workers if address is not None or not owned else None
        capacity = max(1, min(cpus, workers) if workers else cpus)
        tracker = ray.remote(num_cpus=0)(AttemptTracker).remote()
        yield Runtime(ray, tracker, capacity, where, limit)
    finally:
        if tracker is not None:
            with contextlib.suppress(Exception):
                ray.kill(tracker)
        if owned:
            with contextlib.suppress(Exception):
                ray.shutdown()
        if temp is not None:
            shutil.rmtree(temp, ignore_errors=True)
