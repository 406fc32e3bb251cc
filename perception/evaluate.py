"""``perception detect`` and ``perception eval``: run the detector and pose solver over frames.

* :func:`run_detect`: annotated images (or an annotated video) plus ``detections.jsonl`` and
  ``detections.csv``, one row per frame.
* :func:`run_eval`: ``report.json`` (detection rate, per-ID counts, time per frame,
  reprojection error; with ground truth: pose error percentiles, rates and errors binned by
  range and viewing angle, pose jitter on static stretches), ``frames.jsonl``, plots, a contact
  sheet, and with several pipelines a side-by-side comparison (``compare.json``/``.md``).

Every pipeline runs on the same decoded frames in one pass. Pose error is measured on
``T_cam_ds``: translation error = distance between the estimated and true DS origin in the
camera frame (m); rotation error = geodesic angle between the two rotations (deg). Frames are
timed on detection + pose (``ms``), not decoding or drawing.

The config, markers, camera and input are checked before the output folder is claimed
(:func:`dockcore.outdir.claim_output_dir`: locked while the command runs, refused when another
tool made it, temporary files of killed runs removed). Files are written atomically: a failure
part-way leaves earlier complete files (and older versions of the others) intact, and a folder
made for a run that fails before writing anything is removed again. A rerun into its own folder
removes the files of the previous run that it does not write again (compare files, plots,
annotated frames; :func:`dockcore.outdir.tracked_outputs`). The folder's owner is checked up the
tree: a folder inside another tool's output (a synth dataset's ``images/``) is refused.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import check_T
from uwdock.dockcore.config import to_dict, validated
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text
from uwdock.dockcore.outdir import claim_output_dir, tracked_outputs
from uwdock.dockcore.provenance import provenance, write_provenance
from uwdock.perception.dictionary_hint import FrameSampler, dictionary_warning
from uwdock.perception.frame_pipeline import (
    CSV_HEADER,
    CameraResolver,
    FrameProcessor,
    FrameResult,
    MarkerSetup,
    Note,
    PerceptionConfig,
    detection_csv_row,
    detection_row,
    draw_result,
    progress_frames,
    resolve_markers,
    silent_note,
)
from uwdock.perception.groundtruth import FrameTruth
from uwdock.perception.report_plots import (
    COMPARE_COLUMNS,
    EvalRecord,
    ReportConfig,
    compare_rows,
    markdown_table,
    plot_error_vs_range,
    plot_rate_vs_range,
    plot_timeline,
    summarise,
)
from uwdock.perception.video import (
    AnnotatedVideoWriter,
    FrameSource,
    ThumbnailBuffer,
    encode_image,
    open_frames,
    write_contact_sheet,
)

__all__ = [
    "CameraResolver",
    "FrameProcessor",
    "FrameResult",
    "MarkerSetup",
    "PerceptionConfig",
    "ReportConfig",
    "resolve_markers",
    "run_detect",
    "run_eval",
]


# --------------------------------------------------------------------------- detect


def run_detect(
    input_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    setup: MarkerSetup,
    camera: CameraModel | None = None,
    cfg: PerceptionConfig | None = None,
    annotate_frames: bool = True,
    progress: bool | None = None,
    note: Note = silent_note,
    topic: str | None = None,
) -> dict[str, Any]:
    """Detect markers (and poses) in every frame of an input; write the per-frame results.

    Writes into ``out_dir``: ``detections.jsonl`` and ``detections.csv`` (one row per frame,
    corrupt frames flagged), annotated frames (``annotated/<name>`` for images,
    ``annotated.mp4`` (or ``.avi`` where no MP4 encoder exists) for a video), ``config.toml``
    and ``provenance.json``.

    Args:
        input_path: image, image folder or video (see :func:`perception.video.open_frames`).
        out_dir: output folder (created).
        setup: markers and geometry (:func:`resolve_markers`).
        camera: intrinsics; None: the reference camera scaled to the frames (noted).
        cfg: detector, board and report settings.
        annotate_frames: write annotated frames.
        progress: tqdm bar on stderr: True, False, or None (only on a terminal).
        note: receives one-line remarks for stderr.
        topic: the image topic when ``input_path`` is a bag (each row then has ``stamp_ns``).

    Returns:
        Counts (``frames``, ``corrupt_frames``, ``frames_with_detection``, ``frames_with_pose``,
        ``markers_detected_total``) and ``outputs`` (paths written).

    Raises:
        ConfigError: an invalid config (one line naming the field).
        DockError: bad input or camera, no decodable frame at all, or an output folder that
            belongs to another tool or is in use (:func:`dockcore.outdir.claim_output_dir`;
            claimed after the config, markers and input are checked).
    """
    cfg = validated(cfg or PerceptionConfig())
    proc = FrameProcessor(setup, cfg.detector, cfg.board, cfg.pose)
    source = open_frames(input_path, topic)
    written: list[Path] = []  # tracked: a rerun removes the annotated frames it does not write
    try:
        with claim_output_dir(out_dir, "perception detect") as out, tracked_outputs(out, written):
            counts, outputs = _detect_frames(
                source, out, setup, proc, cfg, camera, annotate_frames, progress, note, written
            )
            extra = {"input": str(input_path), "markers": setup.description, "counts": counts}
            write_provenance(out, {"perception": cfg}, extra)
            written.extend([*outputs, out / "config.toml", out / "provenance.json"])
    finally:
        source.close()
    return {**counts, "corrupt_frames": source.corrupt, "outputs": [str(p) for p in outputs]}


def _detect_frames(
    source: FrameSource,
    out: Path,
    setup: MarkerSetup,
    proc: FrameProcessor,
    cfg: PerceptionConfig,
    camera: CameraModel | None,
    annotate_frames: bool,
    progress: bool | None,
    note: Note,
    outputs: list[Path] | None = None,
) -> tuple[dict[str, int], list[Path]]:
    """The frame loop of :func:`run_detect` in a claimed folder: (counts, paths written);
    annotated frames are appended to ``outputs`` as they are written."""
    resolver = CameraResolver(camera, note)
    video = None
    if annotate_frames and source.kind in ("video", "bag"):
        video = AnnotatedVideoWriter(out / "annotated.mp4", source.fps or 10.0)
    counts: dict[str, int] = dict.fromkeys(
        ("frames", "frames_with_detection", "frames_with_pose", "markers_detected_total"), 0
    )
    outputs = [] if outputs is None else outputs
    sampler = FrameSampler()  # for the wrong-dictionary hint
    jsonl, table = out / "detections.jsonl", out / "detections.csv"
    try:
        with atomic_path(jsonl) as tmp_j, atomic_path(table) as tmp_c:
            with tmp_j.open("w", encoding="utf-8") as fj, tmp_c.open("w", newline="") as fc:
                writer = csv.writer(fc)
                writer.writerow(CSV_HEADER)
                for index, name, image in progress_frames(source, progress, "detect"):
                    res = None
                    if image is not None:
                        sampler.offer(image)
                        cam = resolver(image.shape[1], image.shape[0])
                        res = proc.process(image, cam)
                        counts["frames"] += 1
                        counts["frames_with_detection"] += bool(res.detections)
                        counts["frames_with_pose"] += res.T_cam_ds is not None
                        counts["markers_detected_total"] += len(res.detections)
                        if annotate_frames:
                            drawn = draw_result(image, res, cam, setup, cfg.report, name)
                            video = _emit(video, out, name, drawn, outputs)
                    row = detection_row(index, name, res)
                    if source.kind == "bag":
                        row["stamp_ns"] = source.timestamps_ns[index]
                    fj.write(json.dumps(row, separators=(",", ":")) + "\n")
                    writer.writerow(detection_csv_row(row))
            if counts["frames"] == 0:
                raise DockError(f"no decodable frame in {source.path} ({source.corrupt} corrupt)")
        if video is not None:
            closed = video.close()
            if closed is not None:
                outputs.append(closed)
    except BaseException:
        if video is not None:
            video.abort()
        raise
    for warning in source.warnings:
        note(warning)
    if not counts["frames_with_detection"]:
        note(dictionary_warning(setup.dictionary, sampler.frames, sampler.offered, setup.ids))
    return counts, [*outputs, jsonl, table]


def _emit(video, out: Path, name: str, drawn: np.ndarray, outputs: list[Path]):
    """Write one annotated frame to the video (switching to MJPG/AVI if MP4 cannot be opened)
    or as an image file; returns the (possibly new) video writer."""
    if video is None:
        path = out / "annotated" / name
        suffix = path.suffix.lower() if path.suffix else ".png"
        outputs.append(atomic_write_bytes(path, encode_image(drawn, suffix)))
        return None
    try:
        video.write(drawn)
    except DockError:
        if video.frames or video.path.suffix.lower() == ".avi":
            raise
        video = AnnotatedVideoWriter(video.path.with_suffix(".avi"), video.fps)
        video.write(drawn)
    return video


# --------------------------------------------------------------------------- eval


def _truth_lookup(
    truth: dict[int, FrameTruth] | None, kind: str
) -> Callable[[int, str], FrameTruth | None]:
    """Match frames to ground truth: by image file name when the labels name images and the
    input is an image folder, else by frame index."""
    if truth is None:
        return lambda index, name: None
    by_name = {Path(ft.image).name: ft for ft in truth.values() if ft.image}
    if by_name and kind in ("folder", "image"):
        return lambda index, name: by_name.get(name)
    return lambda index, name: truth.get(index)


def _record(index: int, name: str, res: FrameResult, ft: FrameTruth | None) -> EvalRecord:
    corner_errors = []
    if ft is not None:
        labels = {m.marker_id: m for m in ft.markers if m.visible}
        for d in res.detections:
            if d.marker_id in labels:
                diff = d.corners_px - labels[d.marker_id].corners_px
                corner_errors.append(float(np.linalg.norm(diff, axis=1).mean()))
    return EvalRecord(
        frame=index,
        name=name,
        ids=tuple(d.marker_id for d in res.detections),
        ms=res.ms,
        T_cam_ds=res.T_cam_ds,
        rms_px=res.reprojection_rms_px,
        truth=ft,
        corner_errors_px=tuple(corner_errors),
    )


def _write_jsonl(path: Path, rows: Iterable[dict[str, Any]]) -> Path:
    with atomic_path(path) as tmp, tmp.open("w", encoding="utf-8") as fh:
        for row in rows:
            fh.write(json.dumps(row, separators=(",", ":")) + "\n")
    return path


def run_eval(
    input_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    setup: MarkerSetup,
    camera: CameraModel,
    cfg: PerceptionConfig | None = None,
    pipelines: Sequence[str] = ("default",),
    truth: dict[int, FrameTruth] | None = None,
    truth_source: str | None = None,
    progress: bool | None = None,
    note: Note = silent_note,
    T_body_cam: np.ndarray | None = None,
    topic: str | None = None,
) -> dict[str, Any]:
    """Evaluate one or more pipelines on the same frames; write the report.

    Writes into ``out_dir`` (each file atomically, in this order): ``frames.jsonl`` (per frame,
    first pipeline), ``report.json``, with several pipelines ``compare.json`` and
    ``compare.md``, the plots ``timeline.png``, with ground truth ``rate_vs_range.png`` and
    ``error_vs_range.png``, ``contact_sheet.png``, and ``config.toml`` + ``provenance.json``.

    Args:
        input_path: image, image folder or video.
        out_dir: output folder (created).
        setup: markers and geometry (:func:`resolve_markers`).
        camera: intrinsics (scaled to the frames when only the resolution differs).
        cfg: detector, board and report settings (``cfg.detector.pipeline`` is ignored).
        pipelines: pipeline names; the first is the report's main pipeline.
        truth: frame index -> ground truth (:func:`perception.groundtruth.load_ground_truth`).
        truth_source: where the ground truth came from (for the report).
        progress: tqdm bar on stderr: True, False, or None (only on a terminal).
        note: receives one-line remarks for stderr.
        T_body_cam: (4, 4) camera mounting ``T_bodyfrd_camcv``; with it, frames whose ground
            truth records the vehicle pose (``T_world_body``) are estimated with the level-DS
            refinement (``cfg.pose.level_ds``), as the env's camera source does.
        topic: the image topic when ``input_path`` is a bag (``frames.jsonl`` rows then have
            ``stamp_ns``; ground truth from a pose topic:
            :func:`perception.groundtruth.truth_from_bag`).

    Returns:
        The report (also written as ``report.json``).

    Raises:
        ConfigError: an invalid config (one line naming the field).
        DockError: bad input, camera or pipeline; no decodable frame; ground truth that
            matches no frame; an output folder that belongs to another tool or is in use
            (claimed after the config, pipelines and input are checked; a folder made for a
            run that fails is removed again).
    """
    cfg = validated(cfg or PerceptionConfig())
    names = list(dict.fromkeys(pipelines))
    if not names:
        raise DockError("no pipeline to evaluate")
    procs = {
        p: FrameProcessor(setup, dataclasses.replace(cfg.detector, pipeline=p), cfg.board, cfg.pose)
        for p in names
    }
    T_bc = None if T_body_cam is None else check_T(T_body_cam, "T_body_cam")
    source = open_frames(input_path, topic)
    written: list[Path] = []  # tracked: a rerun removes compare files and plots it does not write
    try:
        with claim_output_dir(out_dir, "perception eval") as out, tracked_outputs(out, written):
            return _evaluate(
                source,
                out,
                setup,
                camera,
                cfg,
                procs,
                truth,
                truth_source,
                progress,
                note,
                T_bc,
                written,
            )
    finally:
        source.close()


def _evaluate(
    source: FrameSource,
    out: Path,
    setup: MarkerSetup,
    camera: CameraModel,
    cfg: PerceptionConfig,
    procs: dict[str, FrameProcessor],
    truth: dict[int, FrameTruth] | None,
    truth_source: str | None,
    progress: bool | None,
    note: Note,
    T_body_cam: np.ndarray | None = None,
    written: list[Path] | None = None,
) -> dict[str, Any]:
    """The frame loop and the report of :func:`run_eval`, in a claimed folder; the files are
    appended to ``written`` as they are written."""
    written = [] if written is None else written
    names = list(procs)
    input_path = source.path
    resolver = CameraResolver(camera, note)
    records, sampler, thumbs = _eval_frames(
        source, setup, cfg, procs, _truth_lookup(truth, source.kind), resolver, progress, T_body_cam
    )
    main = records[names[0]]
    _check_eval_frames(source, setup, records, main, sampler, truth, truth_source, note)
    with_truth = truth is not None
    summaries = {p: summarise(records[p], cfg.report, with_truth) for p in names}
    rows = compare_rows(summaries) if len(names) > 1 else None
    extra = {"input": str(input_path), "markers": setup.description, "pipelines": names}
    report: dict[str, Any] = {
        "pipeline": names[0],
        "input": {"path": str(input_path), "kind": source.kind, "frames_total": len(main)},
        **summaries[names[0]],
        "ground_truth": _truth_summary(truth, truth_source, main),
        "compare": rows,
        "camera": {
            "model": to_dict(camera),
            "frame_sizes": [list(k) for k in resolver.sizes],
        },
        "markers": setup.description,
        "config": to_dict(cfg),
        "provenance": provenance({"perception": cfg}, extra),
        "plots": [],
    }
    _write_eval_tables(out, report, main, summaries, rows, source.timestamps_ns, written)
    plots = _write_eval_plots(out, main, summaries, with_truth, thumbs, written)
    report["plots"] = [p.name for p in plots]
    atomic_write_json(out / "report.json", report)
    write_provenance(out, {"perception": cfg}, extra)
    written.extend([out / "config.toml", out / "provenance.json"])
    return report


def _eval_frames(
    source: FrameSource,
    setup: MarkerSetup,
    cfg: PerceptionConfig,
    procs: dict[str, FrameProcessor],
    lookup: Callable[[int, str], FrameTruth | None],
    resolver: CameraResolver,
    progress: bool | None,
    T_body_cam: np.ndarray | None,
) -> tuple[dict[str, list[EvalRecord]], FrameSampler, ThumbnailBuffer]:
    """The one pass over the frames: each pipeline's records, the frames sampled for the
    wrong-dictionary hint and the first pipeline's contact-sheet thumbnails."""
    names = list(procs)
    records: dict[str, list[EvalRecord]] = {p: [] for p in names}
    sampler = FrameSampler()  # for the wrong-dictionary hint
    thumbs = ThumbnailBuffer(cfg.report.contact_sheet_frames, cfg.report.thumbnail_width_px)
    # video frames follow each other: with pose.search_from_prior, each frame searches around
    # the previous frame's DS pose first (a corrupt frame or one without a pose drops the prior)
    follow = cfg.pose.search_from_prior and source.kind in ("video", "bag")
    last_pose: dict[str, np.ndarray | None] = {}
    for index, name, img_bgr in progress_frames(source, progress, "eval"):
        if img_bgr is None:
            last_pose.clear()
            for p in names:
                records[p].append(EvalRecord(index, name, corrupt=True))
            continue
        sampler.offer(img_bgr)
        ft = lookup(index, name)
        cam = resolver(img_bgr.shape[1], img_bgr.shape[0])
        T_world_cam = None
        if T_body_cam is not None and ft is not None and ft.T_world_body is not None:
            T_world_cam = ft.T_world_body @ T_body_cam
        for p, proc in procs.items():
            res = proc.process(img_bgr, cam, T_world_cam, last_pose.get(p))
            if follow:  # the next video frame searches around this frame's DS pose
                last_pose[p] = res.T_cam_ds
            records[p].append(_record(index, name, res, ft))
            if p == names[0] and cfg.report.contact_sheet_frames:
                drawn = (
                    draw_result(img_bgr, res, cam, setup, cfg.report, name)
                    if thumbs.wants()
                    else None
                )
                thumbs.offer(index, name, drawn)
    return records, sampler, thumbs


def _check_eval_frames(
    source: FrameSource,
    setup: MarkerSetup,
    records: dict[str, list[EvalRecord]],
    main: list[EvalRecord],
    sampler: FrameSampler,
    truth: dict[int, FrameTruth] | None,
    truth_source: str | None,
    note: Note,
) -> None:
    """After the pass: the source's warnings and the wrong-dictionary hint noted; no decodable
    frame, or ground truth that matches none, refused."""
    for warning in source.warnings:
        note(warning)
    if not any(not r.corrupt for r in main):
        raise DockError(f"no decodable frame in {source.path} ({source.corrupt} corrupt)")
    if not any(r.ids for rs in records.values() for r in rs):
        note(dictionary_warning(setup.dictionary, sampler.frames, sampler.offered, setup.ids))
    if truth is not None and not any(r.truth is not None for r in main):
        raise DockError(
            f"ground truth {truth_source or ''} matches none of the frames of {source.path} "
            f"(by image name for labelled folders, else by frame index)"
        )


def _truth_summary(
    truth: dict[int, FrameTruth] | None, truth_source: str | None, main: list[EvalRecord]
) -> dict[str, Any] | None:
    """The report's ``ground_truth``: where it came from, its frames and those matched."""
    if truth is None:
        return None
    return {
        "source": truth_source,
        "frames": len(truth),
        "matched": sum(r.truth is not None for r in main),
    }


def _write_eval_tables(
    out: Path,
    report: dict[str, Any],
    main: list[EvalRecord],
    summaries: dict[str, dict[str, Any]],
    rows: list[dict[str, Any]] | None,
    stamps: Sequence[int],
    written: list[Path],
) -> None:
    """``frames.jsonl`` (with a bag's ``stamp_ns``), ``report.json`` and, with several
    pipelines, ``compare.json`` and ``compare.md``."""
    written.append(
        _write_jsonl(
            out / "frames.jsonl",
            (
                {**r.to_json(), "stamp_ns": stamps[k]} if stamps else r.to_json()
                for k, r in enumerate(main)
            ),
        )
    )
    written.append(atomic_write_json(out / "report.json", report))
    if rows is not None:
        written.append(
            atomic_write_json(
                out / "compare.json",
                {"columns": list(COMPARE_COLUMNS), "rows": rows, "summaries": summaries},
            )
        )
        written.append(atomic_write_text(out / "compare.md", markdown_table(rows, COMPARE_COLUMNS)))


def _write_eval_plots(
    out: Path,
    main: list[EvalRecord],
    summaries: dict[str, dict[str, Any]],
    with_truth: bool,
    thumbs: ThumbnailBuffer,
    written: list[Path],
) -> list[Path]:
    """The plots: the timeline, with ground truth the rate and the error by range, and the
    contact sheet (when there is one); returns their paths."""
    plots = [plot_timeline(out / "timeline.png", [r.to_json() for r in main])]
    written.extend(plots)
    if with_truth:
        by_range = {p: s["by_range"] for p, s in summaries.items()}
        plots.append(plot_rate_vs_range(out / "rate_vs_range.png", by_range))
        written.append(plots[-1])
        plots.append(plot_error_vs_range(out / "error_vs_range.png", by_range))
        written.append(plots[-1])
    sheet = write_contact_sheet(out / "contact_sheet.png", thumbs.pick())
    if sheet is not None:
        plots.append(sheet)
        written.append(sheet)
    return plots
