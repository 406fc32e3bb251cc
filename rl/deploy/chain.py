"""The docking chain of the vehicle node, without a transport: inputs by their stamps, a tick
at the policy's rate, the command or the reason it holds.

:class:`DockingChain` is what ``rl node`` (DDS) and ``rl replay`` (a bag) both drive, so a
recorded mission replays exactly what the node would have done. Inputs arrive in any order
with their header stamps (ns); :meth:`DockingChain.tick` runs one control step at a time
``now_ns``:

1. the DS filter predicts over the time since the last tick (the first tick of a run does not);
2. the acoustic fixes received since the last tick are fused, in stamp order (at the start of a
   run whose policy was trained with ``nav.ds_prior = "usbl"``, the first fix is the prior);
3. the newest camera frame stamped at or before ``now_ns`` is decoded, placed with the
   navigation pose *at its own stamp* (a navigation buffer; a frame older than the buffer is
   refused) and measured (detector, board PnP, level re-solve: the simulator's camera source,
   the same code); older frames not yet used are dropped (counted);
4. the observation is built from the newest navigation solution, and the policy's action is
   scaled to the body wrench (:class:`uwdock.rl.deploy.runner.DockingRunner`, shared with the
   simulator's env);
5. the safety checks decide what is published: nothing while disarmed, the wrench when armed
   and every check passes, a zero wrench with the reasons otherwise (camera or navigation
   stale, an input refused recently, the DS estimate too uncertain, an abort, no DS prior, a
   policy output that is not finite).

Everything is a function of the inputs and their stamps: two runs over the same messages give
the same outputs (``rl replay``'s determinism).
"""

from __future__ import annotations

import math
import time
from bisect import bisect_left, insort
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uwdock.calibration.camera import CameraModel, scaled_to_width
from uwdock.calibration.frames import R_from_quat_wxyz, quat_wxyz_from_R
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.inputs import NavSample
from uwdock.rl.deploy.runner import DockingRunner, Odometry
from uwdock.rl.env.obs_sources import Measurement

__all__ = ["DockingChain", "NavBuffer", "Tick"]

_NS = 1_000_000_000


class NavBuffer:
    """Navigation solutions over the last ``span_ns``, looked up at any stamp inside.

    :meth:`at` returns the stored pose at an exact stamp, the interpolation between the two
    neighbours otherwise (position linear, attitude along the shortest rotation), and None for
    a stamp before the oldest sample or after the newest by more than ``hold_ns`` (the newest
    pose is held that long: a frame a moment newer than the navigation).
    """

    def __init__(self, span_ns: int, hold_ns: int) -> None:
        self.span_ns, self.hold_ns = int(span_ns), int(hold_ns)
        self._stamps: list[int] = []
        self._samples: dict[int, NavSample] = {}

    def clear(self) -> None:
        self._stamps.clear()
        self._samples.clear()

    def add(self, sample: NavSample) -> None:
        """Keep ``sample`` (a second sample at the same stamp replaces the first)."""
        if sample.stamp_ns not in self._samples:
            insort(self._stamps, sample.stamp_ns)
        self._samples[sample.stamp_ns] = sample
        cut = self._stamps[-1] - self.span_ns
        while self._stamps and self._stamps[0] < cut:
            del self._samples[self._stamps.pop(0)]

    def latest(self, not_after_ns: int | None = None) -> NavSample | None:
        """The newest sample (stamped at or before ``not_after_ns`` when given)."""
        if not self._stamps:
            return None
        if not_after_ns is None:
            return self._samples[self._stamps[-1]]
        i = bisect_left(self._stamps, not_after_ns + 1) - 1
        return self._samples[self._stamps[i]] if i >= 0 else None

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``T_world_body`` at ``stamp_ns`` (class docstring), or None."""
        s = self._stamps
        if not s or stamp_ns < s[0] or stamp_ns > s[-1] + self.hold_ns:
            return None
        if stamp_ns in self._samples:
            return self._samples[stamp_ns].T_world_body
        if stamp_ns > s[-1]:
            return self._samples[s[-1]].T_world_body
        i = bisect_left(s, stamp_ns)
        a, b = self._samples[s[i - 1]], self._samples[s[i]]
        f = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        return _interpolate(a.T_world_body, b.T_world_body, f)


def _interpolate(Ta: np.ndarray, Tb: np.ndarray, f: float) -> np.ndarray:
    """The pose a fraction ``f`` of the way from ``Ta`` to ``Tb`` (normalised quaternion lerp:
    within 1e-4 rad of the slerp over a 5 Hz step of any AUV)."""
    qa, qb = quat_wxyz_from_R(Ta[:3, :3]), quat_wxyz_from_R(Tb[:3, :3])
    if float(qa @ qb) < 0:
        qb = -qb
    T = np.eye(4)
    T[:3, :3] = R_from_quat_wxyz((1 - f) * qa + f * qb)
    T[:3, 3] = (1 - f) * Ta[:3, 3] + f * Tb[:3, 3]
    return T


@dataclass
class Tick:
    """What one control tick decided.

    Attributes:
        stamp_ns: the tick's time.
        state: ``"disarmed"`` (nothing published), ``"armed"`` (the policy's wrench) or
            ``"holding"`` (a zero wrench; ``reasons`` say why).
        command: (6,) body wrench to publish [N, N m] (FRD), None while disarmed.
        reasons: why the node holds (empty when it does not).
        measurement: this tick's camera measurement of the DS (world NED), or None.
        frame_stamp_ns: the stamp of the frame used this tick, or None.
        detections: markers decoded in it.
        T_world_ds: (4, 4) the filtered DS estimate after this tick.
        cov_xyzyaw: (4, 4) its covariance.
        latency_ms: per stage: ``decode``, ``perception`` (detector + PnP), ``filter``,
            ``policy``, ``total`` (this process's CPU path from tick start to command).
        observation: the policy's input this tick (float32, the env's layout), None without
            a navigation solution or a run.
        values: the diagnostics' key/value pairs.
    """

    stamp_ns: int
    state: str
    command: np.ndarray | None
    reasons: list[str]
    measurement: Measurement | None
    frame_stamp_ns: int | None
    detections: int
    T_world_ds: np.ndarray
    cov_xyzyaw: np.ndarray
    latency_ms: dict[str, float]
    observation: np.ndarray | None = None
    values: dict[str, str] = field(default_factory=dict)


@dataclass
class _Frame:
    stamp_ns: int
    decode: Callable[[], np.ndarray]  # raises ValueError for a frame that does not decode
    compressed: bool | None = None  # JPEG-coded (True), or measured by the detector (None)


class DockingChain:
    """The node's chain (module docstring).

    Args:
        runner: the policy with its estimator, filter and observation
            (:class:`uwdock.rl.deploy.runner.DockingRunner`).
        cfg: the node's settings (safety limits, axes).
        armed: start armed (simulation and tests); a vehicle starts disarmed.
        log: called with one line for each refused input (rate-limited per input kind).
    """

    def __init__(
        self,
        runner: DockingRunner,
        cfg: NodeConfig,
        armed: bool = False,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.runner, self.cfg = runner, cfg
        self.armed, self.aborted = bool(armed), False
        self.log = log or (lambda line: None)
        s = cfg.safety
        self.nav = NavBuffer(round(s.nav_buffer_s * _NS), round(s.nav_timeout_s * _NS))
        self.period_ns = round(_NS / runner.cfg.control_hz)
        self.counts: Counter[str] = Counter()
        self._frames: list[_Frame] = []
        self._usbl: list[tuple[int, np.ndarray, float]] = []
        self._imu: tuple[int, np.ndarray] | None = None
        self._accel: tuple[int, np.ndarray] | None = None
        self._last_frame_ns: int | None = None
        self._last_reject: tuple[int, str] | None = None
        self._last_log_ns: dict[str, int] = {}
        self._prior_ns: int | None = None
        self._usbl_prior = runner.cfg.nav.resolved().ds_prior == "usbl"
        self._last_tick_ns: int | None = None
        self._run_ticks = 0
        self._latencies: deque[float] = deque(maxlen=200)
        self._detected: deque[bool] = deque(maxlen=25)
        self.camera_from_info = False

    # ------------------------------------------------------------------ inputs

    def reject(self, kind: str, reason: str, stamp_ns: int) -> None:
        """Count a refused input, log one line (at most one per kind and second), and hold
        for ``safety.bad_input_hold_s`` from ``stamp_ns``."""
        self.counts[f"refused_{kind}"] += 1
        self._last_reject = (stamp_ns, f"{kind} refused: {reason}")
        last = self._last_log_ns.get(kind)
        if last is None or stamp_ns - last >= _NS or stamp_ns < last:
            self._last_log_ns[kind] = stamp_ns
            n = self.counts[f"refused_{kind}"]
            self.log(f"refused {kind} at {stamp_ns / _NS:.3f} s ({n} so far): {reason}")

    def on_nav(self, sample: NavSample) -> None:
        """A navigation solution (``nav_msgs/Odometry``, read by ``inputs.read_odometry``)."""
        self.counts["nav"] += 1
        self.nav.add(sample)

    def on_imu(self, stamp_ns: int, specific_force_frd_mps2: np.ndarray) -> None:
        """The accelerometer's specific force (FRD, gravity included)."""
        self.counts["imu"] += 1
        if self._imu is None or stamp_ns >= self._imu[0]:
            self._imu = (stamp_ns, specific_force_frd_mps2)

    def on_accel(self, stamp_ns: int, acceleration_frd_mps2: np.ndarray) -> None:
        """The navigation's gravity-free body acceleration."""
        self.counts["accel"] += 1
        if self._accel is None or stamp_ns >= self._accel[0]:
            self._accel = (stamp_ns, acceleration_frd_mps2)

    def on_frame(
        self, stamp_ns: int, decode: Callable[[], np.ndarray], compressed: bool | None = None
    ) -> None:
        """A camera frame, decoded only if it is the one a tick uses; ``compressed``: it came
        JPEG-coded (``CompressedImage``), None: the detector measures it on the frame."""
        self.counts["frames"] += 1
        self._frames.append(_Frame(stamp_ns, decode, compressed))

    def on_usbl(self, stamp_ns: int, p_world_ds_m: np.ndarray, var_m2: float) -> None:
        """An acoustic fix of the DS position (world NED) with its variance per axis."""
        self.counts["usbl"] += 1
        self._usbl.append((stamp_ns, p_world_ds_m, var_m2))

    def on_ds_prior(self, stamp_ns: int, T_world_ds: np.ndarray, var_xyzyaw: np.ndarray) -> None:
        """A mission's DS pose: a new docking run starts from it (zero variances take the
        filter's configured prior)."""
        self.counts["ds_priors"] += 1
        default = np.maximum(self.runner.filter.prior_sigma(), 1e-6) ** 2
        var = np.where(np.asarray(var_xyzyaw) > 0, var_xyzyaw, default)
        self.runner.reset(T_world_ds, var_xyzyaw=var)
        self._prior_ns = stamp_ns
        self._frames = [f for f in self._frames if f.stamp_ns >= stamp_ns]
        self._usbl = [u for u in self._usbl if u[0] >= stamp_ns]
        self._run_ticks = 0

    def on_enable(self, enable: bool) -> None:
        """``std_msgs/Bool`` on the enable topic: arm (clears an abort) or disarm."""
        self.armed = bool(enable)
        self.aborted = False
        self.counts["enable" if enable else "disable"] += 1

    def on_abort(self) -> None:
        """Hold with a zero wrench until the next enable."""
        self.aborted = True
        self.counts["aborts"] += 1

    def on_camera_model(self, camera: CameraModel) -> None:
        """The intrinsics from ``camera_info`` (scaled to the policy's camera width, as the
        simulated world scales its camera)."""
        width = self.runner.cfg.world.camera_width_px
        self.runner.camera = scaled_to_width(camera, width)
        self.camera_from_info = True

    @property
    def damping(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The vehicle's (linear, quadratic) damping (6,) each, from the policy's training env,
        when the config publishes body velocity requests; else None."""
        if not self.cfg.topics.velocity_command:
            return None
        v = self.runner.cfg.world.vehicle
        return np.asarray(v.linear_damping, float), np.asarray(v.quadratic_damping, float)

    # ------------------------------------------------------------------ tick

    def next_tick_ns(self, after_ns: int) -> int:
        """The first tick time at or after ``after_ns`` on the control period's grid."""
        return -(-int(after_ns) // self.period_ns) * self.period_ns

    def tick(self, now_ns: int) -> Tick:
        """One control step at ``now_ns`` (module docstring)."""
        t_start = time.perf_counter()
        lat = {"decode": 0.0, "perception": 0.0, "filter": 0.0, "policy": 0.0}
        r = self.runner
        first = self._run_ticks == 0
        dt_s = 0.0 if first or self._last_tick_ns is None else (now_ns - self._last_tick_ns) / _NS
        self._last_tick_ns = now_ns
        reasons: list[str] = []
        command, obs = None, None
        meas, frame_ns, n_det = None, None, 0
        if self._prior_ns is None or now_ns < self._prior_ns:
            if self._prior_ns is None:
                reasons.append(f"waiting for a DS prior on {self.cfg.topics.ds_prior}")
            else:
                reasons.append("waiting for the run's start (the DS prior's stamp)")
            self._drop_frames_before(now_ns)
        else:
            t = time.perf_counter()
            if dt_s > 0:
                r.filter.predict(dt_s)
            self._fuse_usbl(now_ns, first)
            lat["filter"] += (time.perf_counter() - t) * 1e3
            nav = self.nav.latest(now_ns)
            frame = self._take_frame(now_ns)
            img, T_frame = None, None
            if frame is not None:
                t = time.perf_counter()
                try:
                    img = frame.decode()
                except ValueError as exc:
                    self.reject("image", str(exc), frame.stamp_ns)
                lat["decode"] = (time.perf_counter() - t) * 1e3
                T_frame = self.nav.at(frame.stamp_ns)
                if img is not None and T_frame is None:
                    self.counts["frames_outside_nav"] += 1
                    self.reject("image", "stamped outside the navigation buffer", frame.stamp_ns)
                    img = None
                if img is not None:
                    frame_ns = frame.stamp_ns
                    self._last_frame_ns = frame.stamp_ns
            if nav is None:
                reasons.append("no navigation solution yet")
            else:
                odom = self._odometry(nav)
                t = time.perf_counter()
                obs = r.observe(
                    img,
                    odom,
                    predict=False,
                    T_world_body_frame=T_frame,
                    moved=not first,
                    compressed=None if frame is None else frame.compressed,
                )
                lat["perception"] = (time.perf_counter() - t) * 1e3
                meas, n_det = r.last_measurement, len(r.last_detections) if img is not None else 0
                if img is not None:
                    self.counts["frames_used"] += 1
                    self._detected.append(meas is not None)
                t = time.perf_counter()
                try:
                    command = r.act(obs)
                except ValueError as exc:
                    reasons.append(f"policy: {exc}")
                lat["policy"] = (time.perf_counter() - t) * 1e3
            self._run_ticks += 1
        reasons += self._safety(now_ns)
        if self.aborted:
            reasons.insert(0, "aborted (send enable to resume)")
        state = "disarmed" if not self.armed else ("holding" if reasons else "armed")
        out = None if state == "disarmed" else (np.zeros(6) if reasons else command)
        if out is None or reasons:
            r.prev_action = np.zeros(6)  # the policy's last action is what the vehicle got
        lat["total"] = (time.perf_counter() - t_start) * 1e3
        self._latencies.append(lat["total"])
        self.counts["ticks"] += 1
        if state == "holding":
            self.counts["holding_ticks"] += 1
        tick = Tick(
            now_ns,
            state,
            out,
            reasons,
            meas,
            frame_ns,
            n_det,
            r.filter.T_world_ds,
            r.filter.P.copy(),
            lat,
            None if obs is None else obs.astype(np.float32),
        )
        tick.values = self._values(tick, now_ns)
        return tick

    def _fuse_usbl(self, now_ns: int, first: bool) -> None:
        """Fuse the fixes stamped at or before ``now_ns`` in stamp order; the run's first fix
        is the prior for a policy trained with ``ds_prior = "usbl"``."""
        due = sorted((u for u in self._usbl if u[0] <= now_ns), key=lambda u: u[0])
        self._usbl = [u for u in self._usbl if u[0] > now_ns]
        f = self.runner.filter
        for k, (_, p, var) in enumerate(due):
            if first and k == 0 and self._usbl_prior:
                T = f.T_world_ds
                T[:3, 3] = p
                yaw_var = np.maximum(f.prior_sigma(), 1e-6)[3] ** 2
                f.set_prior_variances(T, np.array([var, var, var, yaw_var]))
            else:
                f.update_position(p, var_m2=var)

    def _take_frame(self, now_ns: int) -> _Frame | None:
        """The newest frame stamped at or before ``now_ns``; older ones are dropped."""
        ready = [f for f in self._frames if f.stamp_ns <= now_ns]
        if not ready:
            return None
        ready.sort(key=lambda f: f.stamp_ns)
        self.counts["frames_dropped"] += len(ready) - 1
        self._frames = [f for f in self._frames if f.stamp_ns > now_ns]
        newest = ready[-1]
        if self._last_frame_ns is not None and newest.stamp_ns <= self._last_frame_ns:
            self.counts["frames_stale"] += 1  # not newer than one already used
            return None
        return newest

    def _drop_frames_before(self, now_ns: int) -> None:
        n = sum(f.stamp_ns <= now_ns for f in self._frames)
        self.counts["frames_dropped"] += n
        self._frames = [f for f in self._frames if f.stamp_ns > now_ns]

    def _odometry(self, nav: NavSample) -> Odometry:
        """The runner's odometry from the newest navigation, acceleration and accelerometer."""
        g_body = nav.T_world_body[:3, :3].T @ np.array([0.0, 0.0, self.runner.gravity_mps2])
        sf = self._imu[1] if self._imu is not None else None
        if self._accel is not None:
            acc = self._accel[1]
        elif sf is not None:
            acc = sf + g_body
        else:
            acc = np.zeros(3)
        return Odometry(
            nav.T_world_body,
            nav.velocity_frd_mps,
            float(nav.angular_velocity_frd_radps[2]),
            acc,
            sf,
        )

    def _safety(self, now_ns: int) -> list[str]:
        """The hold conditions of ``cfg.safety`` at ``now_ns``."""
        s, out = self.cfg.safety, []
        if self._prior_ns is None or now_ns < self._prior_ns:
            return out
        cam_age = None if self._last_frame_ns is None else (now_ns - self._last_frame_ns) / _NS
        if cam_age is None or cam_age > s.camera_timeout_s:
            what = "no frame yet" if cam_age is None else f"newest frame {cam_age:.2f} s old"
            out.append(f"camera stale: {what} (limit {s.camera_timeout_s:g} s)")
        nav = self.nav.latest()
        nav_age = None if nav is None else (now_ns - nav.stamp_ns) / _NS
        if nav_age is None or nav_age > s.nav_timeout_s:
            what = "none yet" if nav_age is None else f"newest {nav_age:.2f} s old"
            out.append(f"navigation stale: {what} (limit {s.nav_timeout_s:g} s)")
        if self._last_reject is not None:
            when, why = self._last_reject
            if 0 <= now_ns - when <= round(s.bad_input_hold_s * _NS):
                out.append(why)
        sigma_xy = float(np.sqrt(max(self.runner.filter.P[0, 0], self.runner.filter.P[1, 1])))
        if not math.isfinite(sigma_xy) or sigma_xy > s.max_ds_sigma_m:
            limit = s.max_ds_sigma_m
            out.append(f"DS estimate too uncertain: {sigma_xy:.2f} m (limit {limit:g} m)")
        return out

    def _values(self, tick: Tick, now_ns: int) -> dict[str, str]:
        """The diagnostics' key/value pairs of a tick."""
        lat = np.array(self._latencies) if self._latencies else np.zeros(1)
        nav = self.nav.latest()

        def age(ns: int | None) -> str:
            return "none" if ns is None else f"{(now_ns - ns) / _NS:.3f}"

        P = tick.cov_xyzyaw
        values: dict[str, Any] = {
            "state": tick.state,
            "reasons": "; ".join(tick.reasons) or "none",
            "armed": str(self.armed).lower(),
            "camera_age_s": age(self._last_frame_ns),
            "nav_age_s": age(None if nav is None else nav.stamp_ns),
            "detections": tick.detections,
            "detection_rate_recent": f"{np.mean(self._detected):.2f}" if self._detected else "0",
            "ds_sigma_xy_m": f"{math.sqrt(max(P[0, 0], P[1, 1])):.4f}",
            "latency_ms": f"{tick.latency_ms['total']:.2f}",
            "latency_p50_ms": f"{np.percentile(lat, 50):.2f}",
            "latency_p99_ms": f"{np.percentile(lat, 99):.2f}",
            "camera_model": "camera_info" if self.camera_from_info else "camera file",
        }
        for k in sorted(self.counts):
            values[f"count_{k}"] = self.counts[k]
        return {k: str(v) for k, v in values.items()}
