"""Per-scene work on a local process pool or on Ray, and the store its shards land in.

Dataset generation, view-cache rendering and flight-vs-teleport runs are embarrassingly parallel over
scenes. Each is ONE module-level task function, a pure function of its item (scene spec, model, seed),
and `map_scenes(task, items, executor)` runs it:

- `Executor("local", jobs=N)`: N spawned processes on this machine (jobs=1: in this process);
- `Executor("ray", address=ADDR)`: Ray tasks (the optional extra `pip install uavsearch[ray]`), on a Ray
  started here (address None) or on a running cluster (`auto`, `ray://head:10001`, KubeRay's head service).

Ray is imported only when asked for. The result is the task's return values in the order of `items`,
whichever executor ran them; progress (tqdm, with ETA) counts finished items as they arrive.

A Store is a folder at a local path or at any fsspec URL (s3://bucket/prefix needs s3fs on every node).
Shards are written whole (local: temporary name + rename; object stores: one PUT), so a killed run
never leaves half a shard, and `npz_bytes` writes numpy archives without timestamps, so equal arrays
are equal bytes and a local run and a Ray run can be compared file by file.
"""

from __future__ import annotations

import atexit
import hashlib
import io
import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
import zipfile
from contextlib import suppress
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

from .cli_args import opt
from .devices import DeviceArgs
from .errors import UavsearchError

EXECUTORS = ("local", "ray")


@dataclass
class ScaleOutArgs(DeviceArgs):
    """The executor flags every per-scene command shares (a base class of its Args dataclass), with the device its
    tensors live on (devices.DeviceArgs)."""
    workers: int = opt(2, "local processes (one per scene in flight)")
    ray: bool = opt(False, "run the per-scene tasks on Ray (pip install uavsearch[ray]); a local Ray unless "
                           "--ray-address")
    ray_address: str | None = opt(None, "join this Ray cluster (auto | HOST:PORT | ray://HOST:10001); implies --ray")


@dataclass(frozen=True)
class Executor:
    """Where map_scenes runs its tasks."""
    kind: str = "local"
    jobs: int = 2  # local processes; for a Ray started here, its CPUs
    address: str | None = None  # Ray cluster to join (None: start one here)

    def __post_init__(self):
        if self.kind not in EXECUTORS:
            raise UavsearchError(f"unknown executor {self.kind!r}; valid: {', '.join(EXECUTORS)}")
        if int(self.jobs) < 1:
            raise UavsearchError("workers must be at least 1")

    @staticmethod
    def from_args(args) -> "Executor":
        """From any object with ScaleOutArgs' fields (an Args dataclass or an argparse namespace)."""
        address = getattr(args, "ray_address", None)
        kind = "ray" if getattr(args, "ray", False) or address else "local"
        return Executor(kind, int(getattr(args, "workers", 2)), address)


def _indexed(job):
    task, i, item = job
    return i, task(item)


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """ray.init retries an unreachable address for many minutes, silently; a mistyped address gets its
    one-line error now."""
    if address in ("auto", "local"):
        return
    host, sep, port = address.split("://", 1)[-1].rpartition(":")
    if not sep or not host or not port.isdigit():
        raise UavsearchError(f"--ray-address must be auto, HOST:PORT or ray://HOST:PORT, not {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise UavsearchError(f"cannot reach the Ray cluster at {address}: {e.strerror or e}") from None


# A Ray started here: its head runs in a child process with these settings in the child's own environment.
# RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 is what keeps Ray from replacing --node-ip-address 127.0.0.1 (and any
# loopback address) by the machine's address; usage statistics are off by --disable-usage-stats.
LOCAL_RAY_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_USAGE_STATS_ENABLED": "0"}
LOCAL_RAY_START_TIMEOUT_S = 120.0


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_local_ray(cpus: int) -> str:
    """Start a Ray head of this machine alone and return the Ray Client address to join it by.

    `ray start --head --block` in a child process: it listens on loopback only, serves no dashboard and
    sends no usage statistics, and nothing of that is set in this process's environment. The driver joins
    it through Ray Client (ray://127.0.0.1:PORT), an address Ray takes as given, where a GCS address on
    127.0.0.1 would be rewritten to the machine's. The head is stopped when this process exits (SIGTERM: it
    drains and ends its own processes)."""
    gcs_port, client_port = _free_loopback_port(), _free_loopback_port()
    log = tempfile.NamedTemporaryFile("w+", prefix="uavsearch-ray-", suffix=".log", delete=False)
    cmd = [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block", "--disable-usage-stats",
           "--include-dashboard", "false", "--node-ip-address", "127.0.0.1", "--port", str(gcs_port),
           "--ray-client-server-port", str(client_port), "--num-cpus", str(int(cpus))]
    head = subprocess.Popen(cmd, env={**os.environ, **LOCAL_RAY_ENV}, stdin=subprocess.DEVNULL, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + LOCAL_RAY_START_TIMEOUT_S
    while True:
        try:
            socket.create_connection(("127.0.0.1", client_port), timeout=1.0).close()
            atexit.register(_stop_local_ray, head, log.name)
            return f"ray://127.0.0.1:{client_port}"
        except OSError:
            pass
        if head.poll() is not None or time.monotonic() > deadline:
            _stop_local_ray(head, None)  # a head that came up too late goes too; its log stays for the reader
            log.seek(0)
            lines = [ln.strip() for ln in log.read().splitlines() if ln.strip()]
            why = lines[-1] if lines else f"exit status {head.returncode}"
            raise UavsearchError(f"cannot start a local Ray (its log: {log.name}): {why}")
        time.sleep(0.2)


def _stop_local_ray(head: subprocess.Popen, log_path: str | None) -> None:
    """Leave the head (a driver still joined would block its drain), then stop it and its processes; remove
    its log (None: keep it)."""
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()
    if head.poll() is None:
        head.terminate()
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
    # What outlives the head in its process group (workers of a raylet it has just ended exit on their own,
    # but not at once on a busy machine) ends with it.
    with suppress(ProcessLookupError, PermissionError):
        os.killpg(head.pid, signal.SIGTERM)
    if log_path is not None:
        with suppress(OSError):
            os.remove(log_path)


def _init_ray(executor: Executor):
    """Import Ray (the optional extra) and connect, once per process: to the cluster at executor.address,
    or to a head started here (_start_local_ray)."""
    try:
        import ray
    except ImportError:
        raise UavsearchError("--ray needs the ray extra: pip install 'uavsearch[ray]'") from None
    if ray.is_initialized():
        return ray
    if executor.address:
        _check_reachable(executor.address)
        address = executor.address
    else:
        address = _start_local_ray(int(executor.jobs))
    try:
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"the Ray cluster at {executor.address}" if executor.address else "a local Ray"
        raise UavsearchError(f"cannot start or join {where}: {str(e).splitlines()[0] if str(e) else e!r}") from None
    return ray


def map_scenes(task: Callable[[Any], Any], items: Sequence, executor: Executor | None = None, *,
               desc: str = "", unit: str = "scene", progress: bool = True,
               on_result: Callable[[int, Any], None] | None = None) -> list:
    """[task(item) for item in items] on the executor; `on_result(i, value)` sees each value as it arrives
    (in completion order, in this process), e.g. to record a finished shard before the next one ends."""
    executor = executor or Executor()
    items = list(items)
    out: list = [None] * len(items)
    ray = _init_ray(executor) if executor.kind == "ray" and items else None  # its errors before any bar
    bar = tqdm(total=len(items), desc=desc, unit=unit, disable=not progress or not items, smoothing=0.1)

    def done(i, value):
        out[i] = value
        if on_result is not None:
            on_result(i, value)
        bar.update(1)

    try:
        if not items:
            return out
        if ray is not None:
            # SPREAD: a scene per node before two on one, so a cluster's nodes all render from the start.
            remote = ray.remote(num_cpus=1, scheduling_strategy="SPREAD", max_retries=2)(task)
            refs = [remote.remote(item) for item in items]
            index = {r: i for i, r in enumerate(refs)}
            pending = list(refs)
            try:
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    for r in ready:
                        done(index[r], ray.get(r))
            except ray.exceptions.RayTaskError as e:
                for r in pending:
                    ray.cancel(r)
                cause = getattr(e, "cause", None)
                if isinstance(cause, UavsearchError):  # the task's own one-line error, as a local run gives it
                    raise cause from None
                raise e.as_instanceof_cause() from None
        elif int(executor.jobs) == 1 or len(items) == 1:
            for i, item in enumerate(items):
                done(i, task(item))
        else:
            # spawn, not fork: the parent may hold torch/OpenMP threads, and each child builds its own
            # PyBullet client (in its own recycled render worker, world.render).
            jobs = [(task, i, item) for i, item in enumerate(items)]
            with mp.get_context("spawn").Pool(min(int(executor.jobs), len(items))) as pool:
                for i, value in pool.imap_unordered(_indexed, jobs):
                    done(i, value)
    finally:
        bar.close()
    return out


# --------------------------------------------------------------------------------------------------
# Bytes


def npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """A .npz archive (np.load reads it) whose bytes depend only on the arrays: numpy.savez stamps each
    member with the wall clock, this writes the zip epoch, so equal arrays give equal files."""
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
    return buf.getvalue()


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def process_tree_cpu_s() -> float:
    """CPU seconds of this process and its children so far, live ones included (a scene renders in a
    child: world.render's recycled worker). Differences of two readings are a task's CPU cost."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    try:
        tick = os.sysconf("SC_CLK_TCK")
        me = os.getpid()
        for pid in os.listdir("/proc"):
            if pid.isdigit():
                try:
                    with open(f"/proc/{pid}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                except OSError:
                    continue
                if int(fields[1]) == me:  # ppid; utime and stime are fields 14 and 15 of stat
                    total += (int(fields[11]) + int(fields[12])) / tick
    except (OSError, ValueError, AttributeError):  # no /proc: the children still running are not counted
        pass
    return total


# --------------------------------------------------------------------------------------------------
# Store


class Store:
    """A folder of shards and small JSON files at a local path or an fsspec URL (picklable: tasks get it)."""

    def __init__(self, url):
        import fsspec  # cheap; s3fs and friends load only for their protocols

        url = os.fspath(url)
        self.fs, root = fsspec.core.url_to_fs(url)
        self.local = "file" in (self.fs.protocol if isinstance(self.fs.protocol, tuple) else (self.fs.protocol,))
        self.root = os.path.abspath(root) if self.local else root.rstrip("/")
        self.url = self.root if self.local else url.rstrip("/")

    def __reduce__(self):
        return Store, (self.url,)

    def __repr__(self) -> str:
        return f"Store({self.url!r})"

    def path(self, key: str) -> str:
        return f"{self.root}/{key}"

    def _fresh(self, path: str) -> str:
        """Object-store filesystems cache listings; other machines write here, so never trust them."""
        if not self.local:
            self.fs.invalidate_cache(path)
        return path

    def exists(self, key: str) -> bool:
        return self.fs.exists(self._fresh(self.path(key)))

    def size(self, key: str) -> int | None:
        try:
            return int(self.fs.size(self._fresh(self.path(key))))
        except (FileNotFoundError, OSError):
            return None

    def read_bytes(self, key: str) -> bytes:
        try:
            return self.fs.cat_file(self.path(key))
        except FileNotFoundError:
            raise UavsearchError(f"{self.path(key)} not found") from None

    def write_bytes(self, key: str, data: bytes) -> None:
        """Whole or not at all: a reader never sees half a file."""
        path = self.path(key)
        if self.local:
            os.makedirs(os.path.dirname(path), exist_ok=True)
            tmp = f"{path}.tmp{os.getpid()}-{uuid.uuid4().hex[:8]}"
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        else:
            self.fs.pipe_file(path, data)

    def read_json(self, key: str) -> dict | None:
        if not self.exists(key):
            return None
        try:
            return json.loads(self.read_bytes(key))
        except json.JSONDecodeError as e:
            raise UavsearchError(f"{self.path(key)} is not valid JSON: {e}") from None

    def write_json(self, key: str, obj) -> None:
        self.write_bytes(key, (json.dumps(obj, indent=1) + "\n").encode())

    def keys(self, prefix: str) -> list[str]:
        """Keys of the files directly under `prefix` (a folder key), temporary files left out, sorted."""
        try:
            names = self.fs.ls(self._fresh(self.path(prefix)), detail=False)
        except FileNotFoundError:
            return []
        out = [f"{prefix}/{n.rstrip('/').rsplit('/', 1)[-1]}" for n in names]
        return sorted(k for k in out if ".tmp" not in k.rsplit("/", 1)[-1])


def manifest_entry(key: str, data: bytes, tag: str) -> dict:
    """What the manifest records of a finished shard."""
    return {"key": key, "sha256": sha256_hex(data), "size": len(data), "tag": tag}


def finished(store: Store, entry: dict | None, tag: str) -> bool:
    """A shard is done when its manifest entry carries this generator tag and the stored file has the
    recorded size (the sha256 is for checking copies; reading every shard back to resume would cost more
    than the resume saves on an object store)."""
    return bool(entry) and entry.get("tag") == tag and store.size(entry["key"]) == entry.get("size")


__all__ = ["EXECUTORS", "Executor", "ScaleOutArgs", "Store", "finished", "manifest_entry", "map_scenes",
           "npz_bytes", "process_tree_cpu_s", "sha256_hex"]
