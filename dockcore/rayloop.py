"""``ray`` kept on the loopback interface: a Ray cluster of several nodes on one machine that
listens on 127.0.0.1 only (to try a cluster out, and for the tests).

Ray 2.60 cannot do this with its own command line: it rewrites ``127.0.0.1`` (``--address``,
``--node-ip-address``, ``ray.init(_node_ip_address=)``) to the machine's routable address
(``ray._private.services.resolve_ip_for_localhost``), and a node whose IP is not exactly
127.0.0.1 binds its gRPC servers to every interface (``*``, ``0.0.0.0``). Its switch
``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` keeps a node on 127.0.0.1 but then refuses
``ray start --address`` (a second node: "Multi-node Ray clusters are not supported on Windows
and OSX"). This runs Ray's own command line with the loopback address kept as given, and every
process it starts (the raylet's agents and workers included) on 127.0.0.1::

    python -m uwdock.dockcore.rayloop start --head --port 6379 --num-cpus 1
    python -m uwdock.dockcore.rayloop start --address 127.0.0.1:6379 --num-cpus 1
    python -m uwdock.dockcore.rayloop status --address 127.0.0.1:6379
    datasets synth ... --backend ray --ray-address 127.0.0.1:6379

Any ``ray`` subcommand and option works (``start`` gets ``--node-ip-address 127.0.0.1`` unless
given, and the head ``--dashboard-host 127.0.0.1``); the toolkit's commands need nothing more
than ``--ray-address 127.0.0.1:PORT`` (:func:`uwdock.dockcore.pool.join_loopback`).
"""

from __future__ import annotations

import os
import sys

__all__ = ["LOOPBACK", "keep_loopback", "main"]

#: The address every listener of a loopback cluster binds.
LOOPBACK = "127.0.0.1"
#: Ray's switch, read when ``ray`` is imported: a node that takes the loopback address.
RAY_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def keep_loopback(allow_join: bool) -> None:
    """In this process (``ray`` imported or not): Ray keeps ``127.0.0.1`` as given instead of
    rewriting it to the routable address, and the processes it starts from here take the
    loopback address too. ``allow_join``: ``ray start --address`` may join a cluster (Ray's
    switch alone refuses a second node)."""
    os.environ[RAY_LOOPBACK_ENV] = "0"  # the processes started from here, and a later import
    import ray._private.ray_constants as ray_constants
    import ray._private.services as services
    from ray._common.network_utils import is_localhost

    original = getattr(services, "_uwdock_resolve", services.resolve_ip_for_localhost)

    def resolve_ip_for_localhost(host: str) -> str:
        return LOOPBACK if host and is_localhost(host) else original(host)

    services._uwdock_resolve = original  # type: ignore[attr-defined]
    services.resolve_ip_for_localhost = resolve_ip_for_localhost
    # read at each call: False makes get_node_ip_address() answer 127.0.0.1 (a driver, `ray
    # status`); `ray start --address` needs True to pass its check (the patch above keeps
    # 127.0.0.1, and a node joining 127.0.0.1 sees itself as 127.0.0.1)
    ray_constants.ENABLE_RAY_CLUSTER = allow_join


def _with_defaults(argv: list[str]) -> list[str]:
    """``ray start`` on 127.0.0.1 unless told otherwise (the head's dashboard too)."""
    if not argv or argv[0] != "start":
        return argv
    given = {a.split("=", 1)[0] for a in argv}
    extra = [] if "--node-ip-address" in given else ["--node-ip-address", LOOPBACK]
    if "--head" in given and "--dashboard-host" not in given:
        extra += ["--dashboard-host", LOOPBACK]
    return [argv[0], *extra, *argv[1:]]


def main(argv: list[str] | None = None) -> None:
    """``ray ARGS...`` on the loopback interface (module docstring)."""
    args = _with_defaults(list(sys.argv[1:] if argv is None else argv))
    keep_loopback(allow_join=bool(args) and args[0] == "start")
    from ray.scripts.scripts import main as ray_main

    sys.argv = ["ray", *args]
    ray_main()


if __name__ == "__main__":
    main()
