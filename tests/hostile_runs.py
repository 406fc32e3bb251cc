"""Helpers of the hostile-input and resume tests: the one-line error check, a dataset folder as
bytes, a training run's files as digests, and a command group run as a real process of its
own."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def assert_refused(res, out: Path | None = None) -> str:
    """``res`` (a :class:`tests.conftest.CliResult`) stopped with exit status 2 and exactly one
    stderr line ``error: ...`` (no traceback); ``out``, when given, was not created. Returns
    the line."""
    lines = res.err.splitlines()
    assert res.code == 2, (res.code, res.err)
    assert len(lines) == 1 and lines[0].startswith("error: "), res.err
    assert "Traceback" not in res.err
    if out is not None:
        assert not out.exists(), f"{out} was created: {sorted(p.name for p in out.iterdir())}"
    return lines[0]


#: A small training run with everything a resume or a worker layout has to carry: envs in
#: worker processes, evaluations (their shares run in the workers) between checkpoints, a
#: curriculum and an asymmetric critic. Format with ``n_envs`` and ``eval_episodes``.
SMALL_RUN = """\
n_envs = {n_envs}
total_steps = 256
checkpoint_every = 128
eval_every = 128
eval_episodes = {eval_episodes}
[env]
episode_s = 4.0
obs_privileged = true
[curriculum]
steps = 192
spawn_scale_start = 0.3
[ppo]
n_steps = 32
batch_size = 64
n_epochs = 2
"""

#: What a training run writes about itself (logs, its owner, timings, a figure's metadata):
#: not part of the run's results.
RUN_BOOKKEEPING = ("tb/", "provenance.json", "resume_log.jsonl", ".uwdock", "eval_history.png")


def run_digest(run: Path) -> dict[str, str]:
    """A training run's files (but for :data:`RUN_BOOKKEEPING`) by relative path -> sha256."""
    out = {}
    for p in sorted(run.rglob("*")):
        rel = p.relative_to(run).as_posix()
        if p.is_file() and not rel.startswith(RUN_BOOKKEEPING):
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones too) by relative path -> its bytes, but for the
    empty lock file, which a claim that was refused may leave (``dockcore.outdir``)."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != ".uwdock.lock"
    }


def dataset(root: Path) -> dict[str, bytes]:
    """A dataset's images (every file in images/, hidden ones too) and labels.jsonl."""
    files = {f"images/{p.name}": p.read_bytes() for p in sorted((root / "images").iterdir())}
    return files | {"labels.jsonl": (root / "labels.jsonl").read_bytes()}


def group_process(group: str, *args: object, **popen: object) -> subprocess.Popen:
    """Start ``<group> <args>`` (e.g. ``datasets synth ...``) as a process of its own running
    this source tree, its output piped."""
    code = f"import sys; sys.argv[0] = {group!r}; from uwdock.{group}.cli import main; main()"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-c", code, *map(str, args)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,
    )


def dead_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    code = "import os; print(os.getpid())"
    proc = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return int(proc.stdout)
