"""What an evaluated episode leaves besides numbers: the onboard camera's frames as a video and
as a captioned contact sheet."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.media import AtomicVideoWriter
from uwdock.perception.video import write_contact_sheet


def write_video(frames: list[np.ndarray], path: Path, fps: float = 5.0) -> Path | None:
    """(H, W, 3) uint8 RGB frames -> MP4 (mp4v) written atomically; None when there is none."""
    if not frames:
        return None
    with AtomicVideoWriter(path, fps) as video:
        for f in frames:
            video.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    return video.path


def write_frames_sheet(
    frames: list[np.ndarray], path: Path, dt_s: float, first_s: float = 0.0, n: int = 8
) -> Path | None:
    """``n`` evenly spaced camera frames of an episode (RGB) as a captioned contact sheet (PNG
    or JPEG, from the suffix of ``path``);
    frame k is captioned with its time ``first_s + k * dt_s``."""
    if not frames:
        return None
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    thumbs = [
        (int(k), f"t = {first_s + k * dt_s:.1f} s", cv2.cvtColor(frames[k], cv2.COLOR_RGB2BGR))
        for k in idx
    ]
    return write_contact_sheet(path, thumbs, cols=4)
