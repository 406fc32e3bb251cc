"""The folder of a ``datasets synth`` run: its state file, which frames are already complete
(a PNG that decodes at the right size and its partial label), the checks that a rerun continues
the same dataset, and the labels assembled in frame order at the end. :mod:`datasets.synth`
renders the frames.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from uwdock.calibration.camera import CameraModel, save_camera
from uwdock.datasets.sequences import FrameSequences
from uwdock.dockcore.config import changed_keys, to_dict
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, special_file_kind
from uwdock.dockcore.provenance import write_provenance
from uwdock.markers.markerset import MarkerSet, save_marker_set

if TYPE_CHECKING:
    from uwdock.datasets.synth_config import SynthConfig

__all__ = [
    "IMAGE_NAME",
    "PARTIAL_DIR",
    "STATE_FILE",
    "assemble_labels",
    "check_folder",
    "done_frames",
    "folder_state",
    "prepare_folder",
]

#: Image and partial-label names of frame k.
IMAGE_NAME = "{:06d}.png"
_IMAGE_RE = re.compile(r"^(\d{6})\.png$")
_PARTIAL_RE = re.compile(r"^(\d{6})\.json$")
PARTIAL_DIR = ".partial"
STATE_FILE = ".synth.json"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _read_jsonl_lenient(path: Path) -> dict[int, str]:
    """frame -> line of an existing labels.jsonl (lines that do not parse are dropped)."""
    out: dict[int, str] = {}
    try:
        if special_file_kind(path) is not None:  # a FIFO would block the read forever
            return out
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return out
    for line in lines:
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict) and isinstance(obj.get("frame"), int):
            out[obj["frame"]] = line.strip() + "\n"
    return out


def folder_state(
    cfg: SynthConfig, poses: np.ndarray | None, sequences: FrameSequences | None = None
) -> dict[str, Any]:
    """What must match for a resume: the config without n_frames, the given poses and their
    sequence labels (a key only when given, so folders of earlier runs still resume)."""
    digest = None
    if poses is not None:
        digest = hashlib.sha1(np.ascontiguousarray(poses, np.float64).tobytes()).hexdigest()
    state = {"config": {**to_dict(cfg), "n_frames": None}, "poses_sha1": digest}
    if sequences is not None:
        text = json.dumps(sequences.to_json(), sort_keys=True).encode()
        state["sequences_sha1"] = hashlib.sha1(text).hexdigest()
    return state


def _check_resume(out_dir: Path, state: dict[str, Any]) -> None:
    """Refuse a folder holding frames of another config (or of no known config)."""
    path = out_dir / STATE_FILE
    if not path.is_file():
        ours = (out_dir / "labels.jsonl", out_dir / PARTIAL_DIR)
        images = out_dir / "images"
        if any(p.exists() for p in ours) or (images.is_dir() and any(images.glob("*.png"))):
            raise DockError(
                f"{out_dir} holds frames of unknown origin (no {STATE_FILE}); use a new --out"
            )
        return
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        reason = " ".join(str(exc).split())
        raise DockError(f"{path}: unreadable ({reason}); use a new --out") from None
    new = json.loads(json.dumps(state))
    if old != new:
        changed = [k.removeprefix("config.").removesuffix("_sha1") for k in changed_keys(old, new)]
        raise DockError(
            f"{out_dir} holds a dataset made with another config (differs in "
            f"{', '.join(changed[:4]) or 'format'}); use a new --out (or the same settings "
            "to resume)"
        )


def _indices(folder: Path, pattern: re.Pattern[str]) -> list[int]:
    """Frame indices of the files in ``folder`` whose names match ``pattern`` (group 1)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return [int(m.group(1)) for m in map(pattern.match, names) if m]


def _check_no_frames_beyond(out_dir: Path, n: int, old_lines: dict[int, str]) -> None:
    """Refuse to shrink a dataset: ``n`` frames into a folder holding frames >= n would delete
    them (images, partial labels or ``old_lines``, those of ``labels.jsonl``)."""
    held = [
        *_indices(out_dir / "images", _IMAGE_RE),
        *_indices(out_dir / PARTIAL_DIR, _PARTIAL_RE),
        *old_lines,
    ]
    last = max(held, default=-1)
    if last >= n:
        raise DockError(
            f"{out_dir} holds frames up to {last} of this dataset: {n} frames would delete "
            f"frames {n}-{last}; ask for {last + 1} or more to resume or extend it, or use "
            "another --out"
        )


def check_folder(out_dir: Path, state: dict[str, Any], n: int) -> dict[int, str]:
    """Everything that must hold before a run writes into ``out_dir`` (read only); returns the
    lines of its ``labels.jsonl`` by frame (empty without one)."""
    if not out_dir.is_dir():
        return {}
    _check_resume(out_dir, state)
    old_lines = _read_jsonl_lenient(out_dir / "labels.jsonl")
    _check_no_frames_beyond(out_dir, n, old_lines)
    return old_lines


def prepare_folder(
    out_dir: Path,
    cfg: SynthConfig,
    camera: CameraModel,
    T_body_cam: np.ndarray,
    marker_set: MarkerSet,
) -> None:
    """Camera file, marker set copy (without render meshes), provenance."""
    save_camera(out_dir / "camera.yaml", camera, T_body_cam)
    plain = MarkerSet(
        tuple(dataclasses.replace(m, render_mesh=None) for m in marker_set.markers),
        dict(marker_set.geometry),
    )
    save_marker_set(out_dir / "markerset.toml", plain)
    write_provenance(out_dir, {"synth": cfg})


def _png_ok(path: Path, size_px: tuple[int, int]) -> bool:
    """True when ``path`` is a whole PNG image of ``size_px`` (width, height).

    Reads the chunk structure and checks every chunk's CRC, the IHDR size and the final IEND,
    without decoding pixels (about 1 ms per MB): an empty, truncated or corrupted file, an
    image of another size, or something other than a regular file (a FIFO), is False.
    """
    try:
        if special_file_kind(path) is not None:  # a FIFO would block the read forever
            return False
        data = memoryview(path.read_bytes())
    except OSError:
        return False
    if bytes(data[:8]) != _PNG_SIGNATURE:
        return False
    pos = 8
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = bytes(data[pos + 4 : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            return False
        if zlib.crc32(data[pos + 4 : end - 4]) != int.from_bytes(data[end - 4 : end], "big"):
            return False
        if pos == 8:
            if kind != b"IHDR" or length < 8:
                return False
            width = int.from_bytes(data[pos + 8 : pos + 12], "big")
            height = int.from_bytes(data[pos + 12 : pos + 16], "big")
            if (width, height) != size_px:
                return False
        if kind == b"IEND":
            return end == len(data)
        pos = end
    return False


def _partial_ok(path: Path, k: int) -> bool:
    """True when ``path`` holds frame k's label: one line of JSON naming the frame."""
    try:
        if special_file_kind(path) is not None:  # a FIFO would block the read forever
            return False
        text = path.read_text(encoding="utf-8")
        obj = json.loads(text)
    except (OSError, ValueError):
        return False
    one_line = text.endswith("\n") and text.count("\n") == 1
    return one_line and isinstance(obj, dict) and obj.get("frame") == k


def done_frames(
    out_dir: Path, n: int, old_lines: dict[int, str], size_px: tuple[int, int]
) -> set[int]:
    """Frames < n whose image and label are both whole (a bad partial label is removed, so
    the frame's line of labels.jsonl, if any, counts instead)."""
    images = out_dir / "images"
    partial = out_dir / PARTIAL_DIR
    done = set()
    for k in range(n):
        label = partial / f"{k:06d}.json"
        has_label = _partial_ok(label, k)
        if not has_label:
            label.unlink(missing_ok=True)
        if (has_label or k in old_lines) and _png_ok(images / IMAGE_NAME.format(k), size_px):
            done.add(k)
    return done


def assemble_labels(out_dir: Path, n: int, old_lines: dict[int, str]) -> None:
    """labels.jsonl from the partial files and the old lines, in frame order; cleanup."""
    partial = out_dir / PARTIAL_DIR
    with atomic_path(out_dir / "labels.jsonl") as tmp, tmp.open("w", encoding="utf-8") as fh:
        for k in range(n):
            p = partial / f"{k:06d}.json"
            fh.write(p.read_text(encoding="utf-8") if p.is_file() else old_lines[k])
    shutil.rmtree(partial, ignore_errors=True)
