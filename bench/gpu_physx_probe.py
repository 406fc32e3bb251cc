"""Can SAPIEN's GPU PhysX run here? A probe for the batched simulator's contact on a GPU.

Usage::

    python bench/gpu_physx_probe.py [--timeout-s 60] [--name gpu_physx_probe] [--out-dir DIR]

SAPIEN 3 ships PhysX's CPU simulation in its wheel, but not PhysX's GPU library
(``libPhysXGpu_64.so``): ``sapien.physx.enable_gpu()`` downloads it from the
``sapien-sim/physx-precompiled`` GitHub releases into ``~/.sapien/physx/<PhysX version>/`` on
first use, and no package index carries it. On a machine that cannot reach GitHub (a cluster
node, the lent GPU machines of this project) GPU PhysX is therefore unavailable unless someone
puts the library there by hand. The probe records, on the machine it runs on:

* the GPU (``nvidia-smi``), SAPIEN's version and its PhysX version;
* whether the library is in SAPIEN's folder, or anywhere under ``$HOME``, ``/usr``, ``/opt``;
* what ``enable_gpu()`` does, in a child process with a deadline (the download has none), and,
  if it succeeds, whether a ``PhysxGpuSystem`` can be created and initialised with one body.

It prints a table and writes ``bench/results/<name>.json`` (machine, commit, packages). The
batched simulator does not depend on any of it: its contact runs on the CPU's PhysX
(``sim/batch.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results

_CHILD = r"""
import json, sys
out = {}
try:
    import sapien, sapien.physx as px
    out["sapien"] = sapien.__version__
    out["physx"] = px.version()
    try:
        px.enable_gpu()
        out["enable_gpu"] = "ok"
    except BaseException as exc:  # requests' errors, OSError from ctypes, RuntimeError
        out["enable_gpu"] = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
    if out["enable_gpu"] == "ok":
        try:
            system = px.PhysxGpuSystem()
            scene = sapien.Scene([system])
            system.set_scene_offset(scene, [0.0, 0.0, 0.0])
            builder = scene.create_actor_builder()
            builder.add_box_collision(half_size=[0.5, 0.5, 0.5])
            builder.build(name="probe")
            system.gpu_init()
            system.step()
            out["gpu_system"] = "ok"
        except BaseException as exc:
            out["gpu_system"] = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
except BaseException as exc:
    out["import"] = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
print("PROBE " + json.dumps(out))
"""


def _gpu_name() -> str:
    if shutil.which("nvidia-smi") is None:
        return "none (no nvidia-smi)"
    try:
        res = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"nvidia-smi failed: {type(exc).__name__}"
    return res.stdout.strip().replace("\n", "; ") or f"nvidia-smi exit {res.returncode}"


#: Where else the library is looked for (a hand-placed copy).
SEARCH_ROOTS = (Path("/usr"), Path("/opt"))


def _find_library(physx_version: str | None, roots: tuple[Path, ...] = SEARCH_ROOTS) -> list[str]:
    """Paths of libPhysXGpu_64.so: SAPIEN's own folder first, then ``$HOME`` and ``roots``."""
    found = []
    if physx_version:
        own = Path.home() / ".sapien" / "physx" / physx_version / "libPhysXGpu_64.so"
        if own.is_file():
            found.append(str(own))
    for root in (Path.home(), *roots):
        if not root.is_dir():
            continue
        for dirpath, _dirs, files in os.walk(root, onerror=lambda _e: None):
            if "libPhysXGpu_64.so" in files:
                p = str(Path(dirpath) / "libPhysXGpu_64.so")
                if p not in found:
                    found.append(p)
    return found


def probe(timeout_s: float, child: str = _CHILD, roots: tuple[Path, ...] = SEARCH_ROOTS) -> dict:
    """The probe's findings (module docstring) as one dict (``child``: the Python code run in
    the child process, printing one ``PROBE {json}`` line; ``roots``: see :func:`_find_library`)."""
    try:
        res = subprocess.run(
            [sys.executable, "-c", child], capture_output=True, text=True, timeout=timeout_s
        )
        lines = [ln for ln in res.stdout.splitlines() if ln.startswith("PROBE ")]
        out = json.loads(lines[-1][6:]) if lines else {"child": f"exit {res.returncode}"}
        if not lines:
            out["stderr"] = " ".join(res.stderr.split())[-300:]
    except subprocess.TimeoutExpired:
        out = {"enable_gpu": f"no answer within {timeout_s:g} s (the download hangs)"}
    out["gpu"] = _gpu_name()
    out["library_found"] = _find_library(out.get("physx"), roots)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timeout-s", type=float, default=60.0)
    ap.add_argument("--name", default="gpu_physx_probe")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args(argv)
    found = probe(a.timeout_s)
    rows = [
        {"what": k, "finding": json.dumps(v) if not isinstance(v, str) else v}
        for k, v in found.items()
    ]
    print(format_table(rows, ["what", "finding"]))
    print("wrote", save_results(a.name, rows, {"timeout_s": a.timeout_s}, a.out_dir))
    print(json.dumps(found))
    return 0


if __name__ == "__main__":
    sys.exit(main())
