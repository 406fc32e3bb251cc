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
  that cannot start (its constructor raises on that node: a missing input file, a package
  missing there) is not replaced forever: after :data:`MAX_START_TRIES` deaths in a row
  without a result, the job stops with one line naming the node and the worker's own error.
  A replacement that cannot even be placed (a node lost and no free CPU left for it) stops the
  job after :data:`REPLACE_TIMEOUT_S` with one line saying so, instead of waiting forever.
  How many workers were replaced is printed when the pool closes (``WorkerPool.replaced``).

Tasks must be deterministic functions of their item (a frame index, an episode index) for the
results not to depend on the backend or the number of workers. Results travel back to the
caller, which writes them (so a cluster needs no shared folder).

Example:
    >>> with worker_pool(PoolConfig("ray", 4), FrameWorker, (cfg_dict,)) as pool:
    ...     for k, (png, label) in pool.imap_unordered("render", range(100)):
    ...         write(k, png, label)
"""

from __future__ import annotations

import atexit
import hashlib
import multiprocessing as mp
import os
import re
import socket
import stat
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from uwdock.dockcore.cli import reclaim_signals
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import quiet_native_stderr
from uwdock.dockcore.procs import die_with_parent

__all__ = [
    "BACKENDS",
    "MAX_START_TRIES",
    "REPLACE_TIMEOUT_S",
    "PoolConfig",
    "WorkerPool",
    "actor_cpus",
    "actor_death",
    "import_ray",
    "kill_actors",
    "loopback_local_ray",
    "preflight",
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
        inputs: files every worker reads (absolute paths): with ``backend = "ray"`` each node
            is checked to hold them with this machine's content before workers start there
            (:func:`check_inputs_on_nodes`).
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


#: Ray's switch (read once, when ``ray`` is imported) that makes a node take the loopback
#: address: a local instance then listens on 127.0.0.1 only, not on every interface.
_RAY_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def loopback_local_ray(address: str | None) -> None:
    """Before ``import ray``: a job that starts its own local Ray instance (``address`` None)
    keeps it on the loopback interface (127.0.0.1), so nothing outside this machine can reach
    it; a job that joins a cluster is left as Ray sets it up. No effect once ``ray`` is
    imported, nor when the variable is already set."""
    if address is None and "ray" not in sys.modules:
        os.environ.setdefault(_RAY_LOOPBACK_ENV, "0")


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


def preflight(cfg: PoolConfig) -> None:
    """Check, before a command writes anything, that its backend can run: the Ray package for
    ``backend = "ray"``, and a reachable head at an explicit ``ray_address`` (a TCP connection
    within 5 s; ``"auto"`` and ``ray://`` client addresses are left to Ray). Raises a one-line
    :class:`DockError`."""
    cfg.validate()
    if cfg.backend != "ray":
        return
    import_ray(cfg.ray_address)
    address = cfg.ray_address
    if address is None or address in ("auto", "local") or "://" in address:
        return
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise DockError(f"--ray-address: expected HOST:PORT, 'auto' or ray://..., got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5.0).close()
    except OSError as exc:
        raise DockError(
            f"cannot reach Ray at {address!r} ({exc.strerror or exc}): is `ray start --head` "
            "running there?"
        ) from None


def start_ray(ray: Any, cpus: int, address: str | None) -> None:
    """Connect this process to Ray once: the cluster at ``address``, or a local instance with
    ``cpus`` CPUs (kept for the process's later pools, shut down at exit). Raises a one-line
    :class:`DockError` when it cannot be started or reached."""
    if ray.is_initialized():
        return
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no network calls home
    kwargs: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "configure_logging": False,
    }
    try:
        # Ray's native client retries a wrong address once a second for ~20 s, each retry a
        # warning on file descriptor 2: its reason is in the one line below instead
        with quiet_native_stderr():
            if address is None:
                ray.init(address="local", num_cpus=cpus, **kwargs)  # a new instance, always
            else:
                ray.init(address=address, **kwargs)
    except Exception as exc:  # ConnectionError, RuntimeError, ValueError ...
        where = "a local Ray instance" if address is None else f"Ray at {address!r}"
        raise DockError(f"cannot start {where}: {' '.join(str(exc).split())}") from None
    reclaim_signals()  # ray.init's native SIGTERM handler dumps a crash report and aborts
    atexit.register(ray.shutdown)


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


class _Host:
    """A Ray actor holding one worker object."""

    def __init__(self, factory: Callable[..., Any], args: tuple) -> None:
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
        check_inputs_on_nodes(ray, inputs)
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
        return self._actor_cls.remote(self._factory, self._args)

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
                # the actor is gone (killed, its node lost, or it could not start): a fresh one
                # takes its slot, and every task it still had goes back to the queue (never
                # yielded twice: a task is yielded only from its own result)
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
