"""Worker pools for the jobs that split into independent tasks: local processes or Ray actors.

The heavy jobs (a dataset's frames, an evaluation's episodes) are tasks that a *worker object*
does one at a time, keeping what is costly to build (a SAPIEN scene, a policy and its env)
between tasks. :func:`worker_pool` starts ``workers`` of them and hands out the tasks
dynamically, one at a time to whichever worker is free, so a worker stuck on long tasks does
not leave the others idle:

* ``backend = "local"``: processes on this machine (``spawn``: SAPIEN must not be forked), each
  dying with the parent whatever killed it (:func:`dockcore.procs.die_with_parent`);
* ``backend = "ray"``: Ray actors (``ray``, the ``uwdock[ray]`` extra), on a local Ray instance
  started for the job or on the cluster at ``ray_address``. A worker whose actor is lost (its
  process killed, its node gone) is replaced by a fresh actor and its unfinished tasks are
  handed out again, so the job completes; each task's result is yielded exactly once. A worker
  that cannot start (its constructor raises on that node: a package that does not import
  there) stops the job at once with one line naming the node and the worker's own error
  (the results yielded so far are the caller's to keep); an actor that keeps dying without a
  result stops it after :data:`MAX_START_TRIES` deaths in a row. A replacement that cannot
  even be placed (a node lost and no free CPU left for it) stops the job after
  :data:`REPLACE_TIMEOUT_S` with one line saying so, instead of waiting forever. How many
  workers were replaced is printed when the pool closes (``WorkerPool.replaced``).

Ray itself is reached safely (:func:`preflight`): an address is checked to be a Ray cluster
that takes this machine's token within seconds (:func:`probe_ray`) before ``ray.init``; a
local instance, and a cluster on this machine's loopback interface, listen on 127.0.0.1 only
(:mod:`dockcore.rayloop`); SIGINT and SIGTERM while Ray starts end the command at once,
with no Ray process left behind (:func:`start_ray`).

Tasks must be deterministic functions of their item (a frame index, an episode index) for the
results not to depend on the backend or the number of workers. The input files a worker reads
travel with it as content (``PoolConfig.inputs``), and results travel back to the caller,
which writes them (so a cluster needs no shared folder).

Example:
    >>> with worker_pool(PoolConfig("ray", 4), FrameWorker, (cfg_dict,)) as pool:
    ...     for k, (png, label) in pool.imap_unordered("render", range(100)):
    ...         write(k, png, label)
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import hashlib
import ipaddress
import multiprocessing as mp
import os
import re
import shutil
import signal
import socket
import stat
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from uwdock.dockcore import numerics
from uwdock.dockcore.cli import reclaim_signals
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import quiet_native_stderr
from uwdock.dockcore.procs import die_with_parent
from uwdock.dockcore.rayloop import LOOPBACK, RAY_LOOPBACK_ENV, keep_loopback

__all__ = [
    "BACKENDS",
    "MAX_START_TRIES",
    "REPLACE_TIMEOUT_S",
    "PoolConfig",
    "WorkerPool",
    "actor_cpus",
    "actor_death",
    "import_ray",
    "is_loopback_host",
    "join_loopback",
    "kill_actors",
    "loopback_local_ray",
    "preflight",
    "probe_ray",
    "start_ray",
    "worker_pool",
]

#: The pool backends.
BACKENDS = ("local", "ray")

#: Tasks handed to one Ray actor ahead of its results (hides the round trip).
_RAY_IN_FLIGHT = 2
#: A worker slot whose actors die this many times in a row without a result stops the job.
MAX_START_TRIES = 3
#: Seconds a replacement actor may take to be placed and built before the job stops (a lost
#: node's work with no free CPU for it anywhere); ``UWDOCK_REPLACE_TIMEOUT_S`` overrides it.
REPLACE_TIMEOUT_S = 90.0
#: Longest blocking wait of the Ray pool's loop (s): Ctrl-C and SIGTERM are handled between.
_RAY_WAIT_S = 1.0


@dataclass(frozen=True)
class PoolConfig:
    """Where a job's workers run.

    Attributes:
        backend: ``"local"`` (processes on this machine) or ``"ray"`` (Ray actors).
        workers: number of workers (processes or actors), 1-1024.
        ray_address: ``backend = "ray"``: the address of a running Ray cluster
            (``ray start --head`` prints it; ``"auto"`` finds the one this machine belongs to);
            None starts a local Ray instance with ``workers`` CPUs for the job.
        inputs: files every worker reads (absolute paths): with ``backend = "ray"`` they travel
            to the nodes as content through Ray's object store and the worker's arguments name
            the copies (:class:`_Host`), so no node needs them at this machine's paths.
    """

    backend: str = "local"
    workers: Annotated[int, Interval(ge=1, le=1024)] = 2
    ray_address: str | None = None
    inputs: tuple[str, ...] = ()

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        if self.backend not in BACKENDS:
            raise ValueError(f"backend: must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if isinstance(self.workers, bool) or not 1 <= int(self.workers) <= 1024:
            raise ValueError(f"workers: must be an integer in [1, 1024], got {self.workers!r}")
        if self.ray_address is not None and self.backend != "ray":
            raise ValueError("ray_address: only with backend = 'ray'")


def actor_death(exc: BaseException) -> tuple[str, str]:
    """(node address, the worker's own error) of a lost Ray actor, from Ray's message: the last
    ``SomethingError: ...`` line of a constructor's traceback, else the message's first line."""
    text = str(exc)
    node = re.search(r"\bip=([0-9A-Za-z.:-]+)", text)
    errors = [
        line.strip()
        for line in text.splitlines()
        if re.match(r"\s*[A-Za-z_][\w.]*(Error|Exception|Exit)\b.*:", line)
    ]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    reason = errors[-1] if errors else (lines[0] if lines else type(exc).__name__)
    return (node.group(1) if node else "unknown"), reason[:300]


class WorkerPool:
    """Started workers; :meth:`imap_unordered` runs tasks on them (see the module docstring).

    Attributes:
        tasks_by_node: Ray: tasks completed per node (``"IP node-id-prefix"`` -> count), so a
            job can show that its work ran where it should; local: empty.
        replaced: Ray: workers replaced after they were lost; local: 0.
    """

    tasks_by_node: dict[str, int]
    replaced: int = 0

    def imap_unordered(self, method: str, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Call ``worker.<method>(item)`` for every item on a free worker; yield ``(item,
        result)`` pairs as they complete. A task's exception is raised here (the pool is then
        shut down by the context manager)."""
        raise NotImplementedError  # pragma: no cover - interface

    def close(self) -> None:
        """Stop the workers."""


# ----------------------------------------------------------------------------- local processes

#: The worker object of a local worker process (built by :func:`_init_local`).
_WORKER: Any = None


def _init_local(parent_pid: int, factory: Callable[..., Any], args: tuple) -> None:
    global _WORKER
    die_with_parent(parent_pid)
    _WORKER = factory(*args)


def _call_local(method: str, item: Any) -> Any:
    return getattr(_WORKER, method)(item)


class _LocalPool(WorkerPool):
    def __init__(self, workers: int, factory: Callable[..., Any], args: tuple) -> None:
        self.tasks_by_node = {}
        self._ex = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_init_local,
            initargs=(os.getpid(), factory, args),
        )

    def imap_unordered(self, method: str, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        futures = {self._ex.submit(_call_local, method, item): item for item in items}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                yield futures[fut], fut.result()

    def close(self) -> None:
        self._ex.shutdown(wait=True, cancel_futures=True)


# ----------------------------------------------------------------------------- Ray actors


#: Seconds the address check (:func:`probe_ray`) waits for a TCP connection, then again for
#: Ray's answer: an address that is not a Ray head is one line within seconds, not Ray's own
#: retries (150 s of silence for a port that is not Ray's, 31 s for ``ray://`` at a closed one).
PROBE_TIMEOUT_S = 4.0
#: Seconds the processes of an interrupted Ray start have after SIGTERM before SIGKILL.
_ABANDON_GRACE_S = 0.5


#: Ray's switch (read once, when ``ray`` is imported) that makes a node take the loopback
#: address: a local instance then listens on 127.0.0.1 only, not on every interface.
_RAY_LOOPBACK_ENV = RAY_LOOPBACK_ENV


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` names this machine's loopback interface (``localhost``, 127.x, ::1)."""
    host = host.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def loopback_local_ray(address: str | None) -> None:
    """Before ``import ray`` (or after, before ``ray.init``): a job that starts its own local
    Ray instance (``address`` None) keeps it on the loopback interface, every listener on
    127.0.0.1, so nothing outside this machine can reach it (:func:`rayloop.keep_loopback`);
    a job that joins a cluster is decided by :func:`join_loopback` once the cluster answered.
    No effect once Ray is initialised."""
    if address is not None:
        return
    if "ray" not in sys.modules:
        os.environ[_RAY_LOOPBACK_ENV] = "0"  # read when ray is imported
        return
    ray = sys.modules["ray"]
    if ray is not None and not ray.is_initialized():
        keep_loopback(allow_join=False)


def join_loopback(address: str, nodes: Sequence[dict[str, Any]]) -> bool:
    """Keep this driver on 127.0.0.1 when it joins a cluster at a loopback ``address`` whose
    alive ``nodes`` (:func:`probe_ray`) all run on 127.0.0.1 (a cluster started with
    ``python -m uwdock.dockcore.rayloop``): Ray would otherwise rewrite the address to the
    machine's routable one, where such a cluster does not listen. Returns whether it did."""
    host = address.rpartition(":")[0]
    if not nodes or not is_loopback_host(host):
        return False
    if any(n["ip"] != LOOPBACK for n in nodes):
        return False  # a cluster on the routable address, reached through loopback: Ray's way
    keep_loopback(allow_join=False)
    return True


def import_ray(address: str | None = "") -> Any:
    """The ``ray`` module, or a one-line :class:`DockError` saying how to install it.
    ``address`` is the job's Ray address (None: a local instance of its own, kept on the
    loopback interface, :func:`loopback_local_ray`)."""
    loopback_local_ray(address)
    try:
        import ray  # the uwdock[ray] extra; only the Ray backend needs it
    except ModuleNotFoundError:
        raise DockError(
            "--backend ray needs the Python package 'ray' (pip install 'uwdock[ray]')"
        ) from None
    return ray


def _split_address(address: str, given: str) -> tuple[str, int]:
    """``(host, port)`` of ``HOST:PORT``, or one line naming the address as ``given``."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise DockError(
            f"--ray-address: expected HOST:PORT, 'auto' or ray://HOST:PORT, got {given!r}"
        )
    return host.strip("[]"), int(port)


def _connect_tcp(address: str, host: str, port: int, timeout_s: float) -> None:
    """A TCP connection to ``host:port`` within ``timeout_s``, or one line."""
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        reason = exc.strerror or str(exc) or type(exc).__name__
        if isinstance(exc, TimeoutError) or "timed out" in reason:
            reason = f"no answer within {timeout_s:g} s"
        raise DockError(
            f"cannot reach Ray at {address!r} ({reason}): is `ray start --head` running there?"
        ) from None


def _auth_line(address: str, exc: BaseException) -> str:
    """One line for a refused or missing token (Ray's own text is a paragraph)."""
    from ray._private.authentication.authentication_utils import is_token_auth_enabled

    if not is_token_auth_enabled():
        return (
            f"Ray at {address!r} requires token authentication: export RAY_AUTH_MODE=token, "
            "with the cluster's token in ~/.ray/auth_token (or RAY_AUTH_TOKEN)"
        )
    text = " ".join(str(exc).split())
    if "couldn't find" in text or "no authentication token" in text.lower():
        return (
            f"RAY_AUTH_MODE=token but no Ray token here for {address!r}: copy the cluster's "
            "~/.ray/auth_token to this machine (or set RAY_AUTH_TOKEN)"
        )
    return (
        f"Ray at {address!r} refused this machine's token: it is not the cluster's (copy the "
        "head's ~/.ray/auth_token here, or set RAY_AUTH_TOKEN to it)"
    )


def _auto_address() -> str:
    """The address ``--ray-address auto`` stands for (``RAY_ADDRESS``, else the cluster this
    machine's last ``ray start`` made), or one line."""
    from ray._private.services import get_ray_address_from_environment

    try:
        found = get_ray_address_from_environment("auto", None)
    except ConnectionError:
        found = None
    if not found or found == "auto":
        raise DockError(
            "--ray-address auto: no Ray cluster found on this machine (start one with "
            "`ray start`, or give its address)"
        )
    return str(found)


def probe_ray(address: str, timeout_s: float = PROBE_TIMEOUT_S) -> list[dict[str, Any]]:
    """Check, within about ``2 * timeout_s``, that ``address`` is a Ray cluster this process
    may join, before ``ray.init`` (whose own retries take minutes on a port that is not Ray's):
    a TCP connection, then Ray's handshake with this process's token where it uses one (the
    head's list of nodes; for a ``ray://`` Ray Client address, a gRPC connection).

    Args:
        address: ``HOST:PORT`` of a head (its GCS), ``"auto"`` (the cluster this machine
            belongs to, as Ray finds it) or ``ray://HOST:PORT``.

    Returns:
        The cluster's alive nodes, ``{"ip", "node_id", "head"}`` each (empty for ``ray://``).

    Raises:
        DockError: one line: a malformed address, no cluster for ``auto``, a closed or silent
            port, a port that is not a Ray head, a token missing or refused.
    """
    import grpc
    from ray._private.grpc_utils import init_grpc_channel

    if address == "auto":
        return probe_ray(_auto_address(), timeout_s)
    scheme, sep, rest = address.partition("://")
    client = bool(sep)
    host, port = _split_address(address if not client else rest if scheme == "ray" else "", address)
    _connect_tcp(address, host, port, timeout_s)
    target = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    not_ray = (
        f"{address!r} is not a Ray {'Client server' if client else 'head'}: no answer to Ray's "
        f"handshake within {timeout_s:g} s (give the address `ray start --head` printed"
        f"{'' if client else ', port 6379 unless --port was given'})"
    )
    try:
        channel = init_grpc_channel(target, options=[("grpc.enable_retries", 0)])
    except Exception as exc:  # AuthenticationError: token mode without a token
        raise DockError(_auth_line(address, exc)) from None
    try:
        if client:
            try:
                grpc.channel_ready_future(channel).result(timeout=timeout_s)
            except grpc.FutureTimeoutError:
                raise DockError(not_ray) from None
            return []
        from ray.core.generated import gcs_service_pb2, gcs_service_pb2_grpc

        stub = gcs_service_pb2_grpc.NodeInfoGcsServiceStub(channel)
        try:
            reply = stub.GetAllNodeInfo(
                gcs_service_pb2.GetAllNodeInfoRequest(), timeout=timeout_s, wait_for_ready=True
            )
        except grpc.RpcError as exc:
            code = exc.code() if callable(getattr(exc, "code", None)) else None
            if code == grpc.StatusCode.UNAUTHENTICATED:
                raise DockError(_auth_line(address, exc)) from None
            raise DockError(not_ray) from None
        except Exception as exc:  # Ray's AuthenticationError: token mode without a token
            if type(exc).__name__ != "AuthenticationError":
                raise
            raise DockError(_auth_line(address, exc)) from None
    finally:
        channel.close()
    alive = [n for n in reply.node_info_list if n.state == 0]  # GcsNodeInfo.ALIVE
    return [
        {"ip": n.node_manager_address, "node_id": n.node_id.hex(), "head": n.is_head_node}
        for n in alive
    ]


def preflight(cfg: PoolConfig, start: bool = True) -> None:
    """Check, before a command writes anything, that its backend can run, and with
    ``backend = "ray"`` bring Ray up: the Ray package, the cluster at ``ray_address``
    answering as a Ray cluster with this machine's token (:func:`probe_ray`, seconds), then
    (``start``) this process connected to it, or a local instance started with
    ``cfg.workers`` CPUs. So a bad address, a missing token, or an interrupt while Ray starts
    leaves no output folder behind. Raises a one-line :class:`DockError`."""
    cfg.validate()
    if cfg.backend != "ray":
        return
    ray = import_ray(cfg.ray_address)
    address = cfg.ray_address
    if address is not None and address != "local":  # checked even when Ray is up already
        if address == "auto":  # as ray.init does for "auto": a token file here turns it on
            from ray._private.authentication.authentication_token_setup import (
                maybe_enable_token_auth_if_token_available,
            )

            maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
        target = _auto_address() if address == "auto" else address
        nodes = probe_ray(target)
        if "://" not in target:
            join_loopback(target, nodes)
    if start:
        start_ray(ray, cfg.workers, address)


def _descendants() -> dict[int, float]:
    """This process's descendants: pid -> start time (a pid reused later is not the same)."""
    import psutil  # installed with the ray extra, like Ray itself

    out: dict[int, float] = {}
    for child in psutil.Process().children(recursive=True):
        try:
            out[child.pid] = child.create_time()
        except psutil.Error:
            pass
    return out


def _end_new_processes(before: dict[int, float], grace_s: float = _ABANDON_GRACE_S) -> None:
    """End the processes an interrupted or failed Ray start left (this process's descendants
    that were not there before it: the GCS, the raylet, its agents and workers): SIGTERM to
    all, SIGKILL to those still there after ``grace_s``. Descendants are collected before any
    is signalled, so an agent is not re-parented away from the list when its raylet ends."""
    import psutil  # installed with the ray extra, like Ray itself

    procs = []
    for child in psutil.Process().children(recursive=True):
        try:
            if before.get(child.pid) != child.create_time():
                procs.append(child)
        except psutil.Error:
            pass
    for p in procs:
        with contextlib.suppress(psutil.Error):
            p.terminate()
    _, alive = psutil.wait_procs(procs, timeout=grace_s)
    for p in alive:
        with contextlib.suppress(psutil.Error):
            p.kill()
    psutil.wait_procs(alive, timeout=grace_s)


@contextmanager
def _signals_kept(ray: Any) -> Iterator[None]:
    """While ``ray.init`` runs: the SIGTERM handler stays the command's. Ray installs its own
    (``sys.exit(15)``: exit 15, no line, its processes orphaned when the signal lands during
    start-up), and its core worker a native one, process-wide (a crash dump, then the handler
    that was there): the command's handlers are installed again after, unconditionally (the
    native one is invisible to ``signal.getsignal``)."""
    utils = ray._private.utils
    original = utils.set_sigterm_handler
    utils.set_sigterm_handler = lambda handler: None
    try:
        yield
    finally:
        utils.set_sigterm_handler = original
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGTERM, signal.SIGINT):
                handler = signal.getsignal(signum)
                if handler is not None:  # None: set outside Python, left alone
                    signal.signal(signum, handler)
        reclaim_signals()


#: Set never: the helper threads that started Ray's processes wait on it for good (see
#: :func:`_interruptible`).
_PARKED = threading.Event()


def _interruptible(call: Callable[[], Any]) -> Any:
    """``call()`` in a helper thread, this thread waiting in short steps: a SIGINT or SIGTERM
    is then handled within moments even while ``ray.init`` blocks in native code for seconds
    (waiting for the GCS it started), where the signal's Python handler would only run after.

    The helper thread then stays, asleep, until the process ends: Ray starts its processes
    with ``PR_SET_PDEATHSIG``, which the kernel fires when the *thread* that started them
    ends, so a helper that returned would take the local Ray instance with it. Interrupted,
    the helper is left to end with the process (a daemon)."""
    box: dict[str, Any] = {}
    done = threading.Event()

    def run() -> None:
        try:
            box["result"] = call()
        except BaseException as exc:  # handed to the waiting thread
            box["error"] = exc
        done.set()
        if "error" not in box:
            _PARKED.wait()  # the processes it started live as long as this thread

    threading.Thread(target=run, name="uwdock-ray-init", daemon=True).start()
    while not done.wait(0.05):
        pass
    if "error" in box:
        raise box["error"]
    return box.get("result")


def start_ray(ray: Any, cpus: int, address: str | None) -> None:
    """Connect this process to Ray once: the cluster at ``address``, or a local instance with
    ``cpus`` CPUs (kept for the process's later pools, shut down at exit). Raises a one-line
    :class:`DockError` when it cannot be started or reached. Interrupted (SIGINT, SIGTERM)
    or failed, the start leaves no Ray process behind: those it started are ended before the
    interrupt or the error goes on (within about 2 s)."""
    if ray.is_initialized():
        return
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no network calls home
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "configure_logging": False,
    }
    loopback_local_ray(address)
    if os.environ.get(numerics.MARK) == "pinned":  # the job's workers run pinned too
        kwargs["runtime_env"] = {"env_vars": numerics.pinned_env_vars()}
    before = _descendants()
    try:
        # Ray's native client retries a wrong address once a second for ~20 s, each retry a
        # warning on file descriptor 2: its reason is in the one line below instead
        with quiet_native_stderr(), _signals_kept(ray):
            if address is None:  # a new instance, always
                kwargs.update(address="local", num_cpus=cpus)
            else:
                kwargs["address"] = address
            _interruptible(lambda: ray.init(**kwargs))
    except BaseException as exc:
        _abandon_start(ray, before)
        if not isinstance(exc, Exception) or isinstance(exc, DockError):
            raise  # an interrupt: the command's one line
        if type(exc).__name__ == "AuthenticationError":
            raise DockError(_auth_line(address or "local", exc)) from None
        where = "a local Ray instance" if address is None else f"Ray at {address!r}"
        raise DockError(f"cannot start {where}: {' '.join(str(exc).split())[:400]}") from None
    atexit.register(ray.shutdown)


def _abandon_start(ray: Any, before: dict[int, float]) -> None:
    """After an interrupted or failed ``ray.init``: the processes it started are ended, and
    Ray's own exit handler is dropped while the start had not finished (it would wait on, or
    abort in, the half-made connection that the helper thread of :func:`_interruptible` may
    still hold); a finished start is shut down as usual, never waited on for long."""
    _end_new_processes(before)
    worker = ray._private.worker
    node = getattr(worker, "_global_node", None)
    if node is not None:  # its processes are gone: forget them, so exit does not wait on them
        with contextlib.suppress(Exception):
            node.all_processes.clear()
    if not ray.is_initialized():
        atexit.unregister(worker.shutdown)
        return
    done = threading.Event()

    def shutdown() -> None:
        with contextlib.suppress(BaseException):
            ray.shutdown()
        done.set()

    threading.Thread(target=shutdown, daemon=True).start()
    done.wait(_ABANDON_GRACE_S)


def file_digests(paths: Sequence[str]) -> list[str | None]:
    """sha256 of each file, None where it is missing or not a regular file (what a node has)."""
    out: list[str | None] = []
    for p in paths:
        try:
            if not stat.S_ISREG(os.stat(p).st_mode):
                raise OSError
            h = hashlib.sha256()
            with open(p, "rb") as f:
                for chunk in iter(lambda f=f: f.read(1 << 20), b""):
                    h.update(chunk)
            out.append(h.hexdigest())
        except OSError:
            out.append(None)
    return out


#: Seconds :func:`check_inputs_on_nodes` waits for every node's answer.
NODE_CHECK_TIMEOUT_S = 60.0


def check_inputs_on_nodes(ray: Any, paths: Sequence[str | os.PathLike[str]]) -> int:
    """Check that every node of the connected Ray cluster holds each input file at its absolute
    path with the driver's content, before work starts there (a zero-CPU task pinned to each
    alive node). Returns the number of nodes checked.

    Raises:
        DockError: one line naming the node and the path missing or different there (what to
            do: a storage path every node mounts, or a copy), or a node that did not answer.
    """
    paths = sorted({str(Path(p).resolve()) for p in paths})
    if not paths:
        return 0
    want = file_digests(paths)
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    probe = ray.remote(num_cpus=0, max_retries=0)(file_digests)
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    refs = [
        probe.options(
            scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)
        ).remote(paths)
        for n in nodes
    ]
    try:
        answers = ray.get(refs, timeout=NODE_CHECK_TIMEOUT_S)
    except ray.exceptions.GetTimeoutError:
        raise DockError(
            f"a Ray node did not answer the input check within {NODE_CHECK_TIMEOUT_S:g} s "
            "(`ray status` shows the cluster)"
        ) from None
    for node, got in zip(nodes, answers, strict=True):
        where = node.get("NodeManagerAddress", node["NodeID"][:12])
        for path, w, g in zip(paths, want, got, strict=True):
            if g is None:
                raise DockError(
                    f"input {path} is not on Ray node {where}: put it on storage every node "
                    "mounts at the same path, or copy it there"
                )
            if g != w:
                raise DockError(
                    f"input {path} on Ray node {where} differs from this machine's (sha256 "
                    f"{g[:12]} against {w[:12] if w else 'none'}): copy it there again"
                )
    return len(nodes)


def actor_cpus(ray: Any, actors: int) -> float:
    """CPUs each of ``actors`` actors asks for: one, or an equal share when the Ray instance has
    fewer CPUs than actors (so they all start instead of waiting for a free CPU forever)."""
    total = float(ray.cluster_resources().get("CPU", 1.0))
    return 1.0 if total >= actors else max(total / actors, 0.01)


def kill_actors(ray: Any, actors: Iterable[Any]) -> None:
    """Kill Ray actors for good (no restart), skipping those already gone."""
    for a in actors:
        try:
            ray.kill(a, no_restart=True)
        except Exception:  # an actor already gone
            pass


def read_inputs(paths: Iterable[str | os.PathLike[str]]) -> dict[str, bytes]:
    """The content of a job's input files, by absolute path (what travels to Ray's nodes
    through the object store, :class:`_Host`).

    Raises:
        DockError: one line naming a file that is missing, not a regular file or unreadable.
    """
    out: dict[str, bytes] = {}
    for p in sorted({str(Path(p).expanduser().resolve()) for p in paths}):
        try:
            if not stat.S_ISREG(os.stat(p).st_mode):
                raise DockError(f"input {p} is not a regular file")
            with open(p, "rb") as f:
                out[p] = f.read()
        except OSError as exc:
            raise DockError(f"input {p}: {exc.strerror or exc}") from None
    return out


#: Where a node keeps the input files jobs sent it, one folder per content (reused by the
#: job's other workers there and by later jobs with the same inputs).
INPUTS_DIR_PREFIX = "uwdock-ray-inputs-"


def materialize_inputs(files: dict[str, bytes], base: str | os.PathLike[str] | None = None) -> Path:
    """On a worker: ``files`` (absolute path -> bytes, :func:`read_inputs`) written under a
    folder of this node's temp dir (or of ``base``) at their own absolute paths
    (``ROOT/abs/path``), so files that name each other relatively (a marker set and its meshes,
    a policy and its run config) still do. The folder is named by the content and written once
    (atomically); returns it."""
    h = hashlib.sha256()
    for path in sorted(files):
        h.update(path.encode("utf-8", "surrogateescape") + b"\0")
        h.update(hashlib.sha256(files[path]).digest())
    if base is not None:
        base = Path(base)
        base.mkdir(parents=True, exist_ok=True)
    else:
        base = Path(tempfile.gettempdir()) / f"{INPUTS_DIR_PREFIX}{os.getuid()}"
        base.mkdir(mode=0o700, exist_ok=True)
        if base.stat().st_uid != os.getuid():  # another user's folder: one of our own
            base = Path(tempfile.mkdtemp(prefix=INPUTS_DIR_PREFIX))
    root = base / h.hexdigest()[:24]
    if root.is_dir():
        return root
    tmp = Path(tempfile.mkdtemp(prefix=".partial-", dir=base))
    for path, data in files.items():
        target = tmp / path.lstrip("/")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    try:
        os.rename(tmp, root)
    except OSError:  # another worker of this node was first: its copy is the same
        shutil.rmtree(tmp, ignore_errors=True)
    return root


def relocate(obj: Any, mapping: dict[str, str]) -> Any:
    """``obj`` with every string that is a key of ``mapping`` replaced by its value, through
    dicts, lists, tuples and dataclasses (a worker's arguments naming input files)."""
    if isinstance(obj, str):
        return mapping.get(obj, obj)
    if isinstance(obj, dict):
        return {k: relocate(v, mapping) for k, v in obj.items()}
    if isinstance(obj, list):
        return [relocate(v, mapping) for v in obj]
    if isinstance(obj, tuple) and not hasattr(obj, "_fields"):
        return tuple(relocate(v, mapping) for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {
            f.name: relocate(getattr(obj, f.name), mapping)
            for f in dataclasses.fields(obj)
            if f.init
        }
        return dataclasses.replace(obj, **changes)
    return obj


def input_mapping(files: Iterable[str], root: Path) -> dict[str, str]:
    """Each input file and the folder holding it -> its copy under ``root``."""
    mapping: dict[str, str] = {}
    for path in files:
        mapping[path] = str(root / path.lstrip("/"))
        folder = os.path.dirname(path)
        mapping.setdefault(folder, str(root / folder.lstrip("/")))
    return mapping


class _Host:
    """A Ray actor holding one worker object. The job's input files come with it as content
    (``files``: an object-store reference Ray resolves to ``{absolute path: bytes}``): written
    on this node (:func:`materialize_inputs`), the paths in ``args`` that name them or their
    folders are changed to the copies before the worker is built, so no node needs the
    driver's files at the driver's paths."""

    def __init__(
        self, factory: Callable[..., Any], args: tuple, files: dict[str, bytes] | None = None
    ) -> None:
        if files:
            args = relocate(args, input_mapping(files, materialize_inputs(files)))
        self.worker = factory(*args)

    def call(self, method: str, item: Any) -> Any:
        return getattr(self.worker, method)(item)

    def ready(self) -> bool:
        """Answered once the actor is placed and its worker built."""
        return True

    def node(self) -> str:
        """Where the actor runs: ``"IP node-id-prefix"``."""
        import ray

        return f"{ray.util.get_node_ip_address()} {ray.get_runtime_context().get_node_id()[:8]}"


class _RayPool(WorkerPool):
    def __init__(
        self,
        workers: int,
        factory: Callable[..., Any],
        args: tuple,
        address: str | None,
        inputs: Sequence[str] = (),
    ) -> None:
        ray = self._ray = import_ray(address)
        start_ray(ray, workers, address)
        # the input files travel as content, once through the object store (:class:`_Host`)
        self._files = ray.put(read_inputs(inputs)) if inputs else None
        self._actor_cls = ray.remote(num_cpus=actor_cpus(ray, workers))(_Host)
        self._factory, self._args = factory, args
        self.actors = [self._new_actor() for _ in range(workers)]
        self.replaced = 0
        self.tasks_by_node = {}
        self._node_of: list[str | None] = [None] * workers  # each slot's actor's node, once asked
        self._deaths_in_row = [0] * workers
        #: replacement actors not yet answering: their ready() reference -> start deadline
        self._starting: dict[Any, float] = {}
        timeout = os.environ.get("UWDOCK_REPLACE_TIMEOUT_S")
        self._replace_timeout_s = float(timeout) if timeout else REPLACE_TIMEOUT_S

    def _new_actor(self) -> Any:
        return self._actor_cls.remote(self._factory, self._args, self._files)

    def _count(self, slot: int) -> None:
        """One more task done on the node of ``slot``'s actor (asked once per actor)."""
        if self._node_of[slot] is None:
            try:
                self._node_of[slot] = self._ray.get(self.actors[slot].node.remote(), timeout=30)
            except Exception:  # lost meanwhile: counted as unknown, asked again next time
                pass
        where = self._node_of[slot] or "unknown"
        self.tasks_by_node[where] = self.tasks_by_node.get(where, 0) + 1

    def _check_starting(self, now: float) -> None:
        """Stop the job when a replacement actor has not started by its deadline."""
        if any(now > deadline for deadline in self._starting.values()):
            raise DockError(
                f"a lost Ray worker could not be started again within "
                f"{self._replace_timeout_s:g} s: no free CPU for it on the cluster (a node "
                "lost?); `ray status` shows what is left. Run the command again when there is "
                "room (datasets synth and rl train --resume go on from what is written)"
            )

    def imap_unordered(self, method: str, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        ray = self._ray
        queue = deque(items)
        running: dict[Any, tuple[int, Any]] = {}  # object ref -> (actor slot, item)
        load = [0] * len(self.actors)

        def fill() -> None:
            for slot in range(len(self.actors)):
                while queue and load[slot] < _RAY_IN_FLIGHT:
                    item = queue.popleft()
                    running[self.actors[slot].call.remote(method, item)] = (slot, item)
                    load[slot] += 1

        fill()
        while running:
            ready, _ = ray.wait([*running, *self._starting], num_returns=1, timeout=_RAY_WAIT_S)
            self._check_starting(time.monotonic())
            if not ready:
                continue
            ref = ready[0]
            if ref in self._starting:  # a replacement is up (or died: its task says which)
                del self._starting[ref]
                continue
            slot, item = running.pop(ref)
            load[slot] -= 1
            try:
                result = ray.get(ref)
            except ray.exceptions.RayActorError as exc:
                if getattr(exc, "actor_init_failed", False):
                    # its worker could not be built there (a package that does not import on
                    # that node, ...): no replacement on that node would do better
                    raise DockError(self._cannot_start(slot, exc)) from None
                # the actor is gone (killed, its node lost): a fresh one takes its slot, and
                # every task it still had goes back to the queue (never yielded twice: a
                # task is yielded only from its own result)
                self._deaths_in_row[slot] += 1
                if self._deaths_in_row[slot] >= MAX_START_TRIES:
                    node, reason = actor_death(exc)
                    raise DockError(
                        f"a Ray worker on node {node} died {self._deaths_in_row[slot]} times in "
                        f"a row without finishing a task: {reason}"
                    ) from None
                queue.appendleft(item)
                lost = [r for r, (s, _) in running.items() if s == slot]
                for r in lost:
                    queue.appendleft(running.pop(r)[1])
                load[slot] = 0
                self._ray.kill(self.actors[slot], no_restart=True)
                self.actors[slot] = self._new_actor()
                self._node_of[slot] = None
                deadline = time.monotonic() + self._replace_timeout_s
                self._starting[self.actors[slot].ready.remote()] = deadline
                self.replaced += 1
            except ray.exceptions.RayTaskError as exc:  # the task raised: raise its own error
                cause = getattr(exc, "cause", None)
                raise (cause if isinstance(cause, Exception) else exc) from None
            else:
                self._deaths_in_row[slot] = 0
                self._count(slot)
                yield item, result
            fill()

    def _cannot_start(self, slot: int, exc: BaseException) -> str:
        """One line for a worker whose constructor failed: the node (IP and node ID, as Ray
        records the actor) and the worker's own error."""
        ip, reason = actor_death(exc)
        node = ""
        actor_id = getattr(exc, "actor_id", None)
        if actor_id:
            with contextlib.suppress(Exception):  # Ray's record of the actor, where it was
                info = self._ray._private.state.actors(actor_id)
                address = info.get("Address") or {}
                ip = address.get("IPAddress") or ip
                node = address.get("NodeID") or ""
        where = f"{ip} (node {node[:8]})" if node else ip
        return (
            f"Ray node {where} cannot run a worker: {reason}. Give that node the same Python "
            "environment as this machine's (or take it out of the cluster), then run the "
            "command again: what is finished is kept"
        )

    def close(self) -> None:
        kill_actors(self._ray, self.actors)
        if self.replaced:
            print(f"note: {self.replaced} lost Ray worker(s) replaced", file=sys.stderr)


@contextmanager
def worker_pool(
    cfg: PoolConfig, factory: Callable[..., Any], args: tuple = ()
) -> Iterator[WorkerPool]:
    """Start ``cfg.workers`` workers, each holding ``factory(*args)`` (a picklable class or
    function importable by the workers), and stop them on exit (an exception included).

    The commands call :func:`preflight` before they write anything; this only starts (or
    joins) Ray.

    Raises:
        DockError: the Ray backend without the ``ray`` package, or a Ray instance that cannot
            be started or reached.
    """
    cfg.validate()
    if cfg.backend == "ray":
        pool: WorkerPool = _RayPool(cfg.workers, factory, args, cfg.ray_address, cfg.inputs)
    else:
        pool = _LocalPool(cfg.workers, factory, args)
    try:
        yield pool
    finally:
        pool.close()
