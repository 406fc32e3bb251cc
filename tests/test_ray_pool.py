"""The Ray pool when a lost worker cannot be replaced (no free CPU for it: a node gone): the job
stops in bounded time with one line, instead of waiting forever (issue 32). Run in a
subprocess: Ray's local instance stays out of the test process."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

pytest.importorskip("ray")

SCRIPT = r"""
import os, pathlib, signal, sys, time
os.environ["UWDOCK_REPLACE_TIMEOUT_S"] = "8"
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.pool import PoolConfig, worker_pool

flag = pathlib.Path(sys.argv[1])

class Worker:
    def __init__(self, flag):
        if pathlib.Path(flag).exists():
            time.sleep(3600)  # a replacement that is never up, as one with no CPU to run on
    def work(self, k):
        time.sleep(0.2)
        return os.getpid()

done = set()
try:
    with worker_pool(PoolConfig("ray", 2), Worker, (str(flag),)) as pool:
        for k, pid in pool.imap_unordered("work", range(60)):
            done.add(k)
            if len(done) == 4:
                flag.touch()
                os.kill(pid, signal.SIGKILL)
                print(f"killed {time.monotonic()}", flush=True)
except DockError as exc:
    print(f"error {time.monotonic()} {exc}", flush=True)
    sys.exit(2)
print("finished", len(done))
"""


def test_a_worker_that_cannot_be_replaced_stops_the_job_in_bounded_time(tmp_path) -> None:
    t0 = time.monotonic()
    res = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path / "no_room")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 2, (res.stdout, res.stderr[-2000:])
    lines = dict(line.split(" ", 1) for line in res.stdout.splitlines() if " " in line)
    killed = float(lines["killed"])
    at, message = lines["error"].split(" ", 1)
    assert 8.0 <= float(at) - killed < 30.0  # the replacement's deadline, then one line
    assert "could not be started again within 8 s" in message and "\n" not in message
    assert time.monotonic() - t0 < 200
