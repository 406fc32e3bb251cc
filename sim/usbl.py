"""The simulated acoustic (USBL) positioning of the docking station.

An ultra-short-baseline system measures the slant range (time of flight) and the direction
(phase differences across its small receiver array) from a transceiver to a transponder. Here the
transceiver rides on the vehicle (body origin, FRD) and the transponder sits at the DS origin;
the vehicle turns each measurement into a fix of the DS position in the world (NED) with its own
navigation, and fuses it as if it described the present.

What a fix gets wrong (:class:`UsblConfig`, one field per effect; each effect set to zero makes
no random draw, so the ``"ideal"`` preset draws exactly what the env drew before this module):

* isotropic noise: N(0, (``sigma_floor_m`` + ``sigma_per_m`` * r)^2) on each world axis (the
  env's original, deliberately kind model; r is the slant range, m);
* range noise: N(0, (``range_sigma_m`` + ``range_sigma_per_m`` * r)^2) along the line of sight;
* bearing noise: the direction turned by N(0, ``bearing_sigma_deg``^2) about each of the two axes
  across the line of sight, so the lateral error grows as r * sigma;
* a per-episode bias, drawn at :meth:`UsblSensor.reset`: a misalignment of the transceiver
  (roll and pitch ~ N(0, ``tilt_bias_sigma_deg``^2), yaw ~ N(0, ``heading_bias_sigma_deg``^2)),
  a range scale error 1 + N(0, ``range_scale_sigma_rel``^2) (sound speed) and a range offset
  N(0, ``range_offset_sigma_m``^2) (clock drift of one-way ranging);
* outliers (multipath): with probability ``outlier_prob`` the fix moves by
  N(0, ``outlier_sigma_m``^2) on each world axis;
* dropouts: with probability ``dropout_prob`` a scheduled fix never arrives;
* latency: a fix delivered at t describes the geometry at t - ``latency_s`` but is placed with
  the vehicle's position at t (its navigation fuses it as current), so it is off by the
  vehicle's displacement over the latency.

Fixes are scheduled every ``period_s`` of simulated time (the first one at the first call after
:meth:`UsblSensor.reset`). The standard deviation a fix carries (what the filter is told) is the
datasheet-style accuracy at its range: noise and bias spreads together, outliers and latency not.

Presets (:data:`USBL_PRESETS`) hold the figures of published systems; each names its source.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from uwdock.calibration.frames import R_from_rpy, cross3
from uwdock.dockcore.config import check_fields
from uwdock.dockcore.domains import Fraction, Interval

__all__ = ["USBL_PRESETS", "UsblConfig", "UsblFix", "UsblSensor"]

_Sigma_m = Annotated[float, Interval(ge=0, le=100)] | None
_PerM = Annotated[float, Interval(ge=0, le=1)] | None  # m per m of slant range
_Angle_deg = Annotated[float, Interval(ge=0, le=45)] | None

#: Two times closer than this are the same instant (s): control-step times are sums of substeps.
_TIME_EPS_S = 1e-6


@dataclass(frozen=True)
class UsblConfig:
    """The acoustic positioning model: a named preset, with any field given here overriding it.

    A field left ``None`` takes the preset's value (:meth:`resolved` fills them in), so a TOML
    ``[usbl]`` table reads ``preset = "cerulean-rovl"`` plus only the values that differ.

    Attributes:
        preset: the base model, a key of :data:`USBL_PRESETS` ("ideal": the env's original
            unbiased fixes).
        period_s: a fix every this many seconds of simulated time (s); 0 disables the fixes.
        sigma_floor_m: isotropic noise on each world axis at zero range (m).
        sigma_per_m: growth of that noise with slant range (m per m).
        range_sigma_m: slant-range noise at zero range (m).
        range_sigma_per_m: growth of the slant-range noise with range (m per m).
        bearing_sigma_deg: direction noise about each axis across the line of sight (deg).
        tilt_bias_sigma_deg: per-episode roll and pitch misalignment of the transceiver (deg).
        heading_bias_sigma_deg: per-episode yaw misalignment (heading reference error, deg).
        range_scale_sigma_rel: per-episode relative range scale error (sound speed, -).
        range_offset_sigma_m: per-episode slant-range offset (clock drift, m).
        outlier_prob: probability that a fix is a multipath outlier (-).
        outlier_sigma_m: displacement of an outlier on each world axis (m).
        dropout_prob: probability that a scheduled fix is lost (-).
        latency_s: age of the geometry a fix describes when it arrives (s).
    """

    preset: str = "ideal"
    period_s: Annotated[float, Interval(ge=0, le=3600)] | None = None
    sigma_floor_m: _Sigma_m = None
    sigma_per_m: _PerM = None
    range_sigma_m: _Sigma_m = None
    range_sigma_per_m: _PerM = None
    bearing_sigma_deg: _Angle_deg = None
    tilt_bias_sigma_deg: _Angle_deg = None
    heading_bias_sigma_deg: Annotated[float, Interval(ge=0, le=180)] | None = None
    range_scale_sigma_rel: Annotated[float, Interval(ge=0, le=0.5)] | None = None
    range_offset_sigma_m: _Sigma_m = None
    outlier_prob: Fraction | None = None
    outlier_sigma_m: Annotated[float, Interval(ge=0, le=1000)] | None = None
    dropout_prob: Fraction | None = None
    latency_s: Annotated[float, Interval(ge=0, le=60)] | None = None

    def validate(self) -> None:
        """Raise ValueError for an unknown preset name."""
        if self.preset not in USBL_PRESETS:
            raise ValueError(
                f"preset: unknown USBL preset {self.preset[:100]!r} "
                f"(known: {', '.join(USBL_PRESETS)})"
            )

    def resolved(self, **base: float) -> UsblConfig:
        """This model with every field set: the preset's values, then ``base`` (values a caller
        puts in place of the preset's), then the fields set here."""
        self.validate()
        values = {name: getattr(USBL_PRESETS[self.preset], name) for name in MODEL_FIELDS}
        unknown = set(base) - set(MODEL_FIELDS)
        if unknown:
            raise ValueError(f"{sorted(unknown)[0]}: not a field of the USBL model")
        values.update(base)
        values.update({n: v for n in MODEL_FIELDS if (v := getattr(self, n)) is not None})
        return UsblConfig(preset=self.preset, **values)


#: The fields of the model proper (all but ``preset``).
MODEL_FIELDS: tuple[str, ...] = tuple(
    f.name for f in dataclasses.fields(UsblConfig) if f.name != "preset"
)

_QUIET = dict.fromkeys(MODEL_FIELDS, 0.0)

#: Named acoustic models. Figures marked *nominal* are ours (no published value was found);
#: the others name their source.
USBL_PRESETS: dict[str, UsblConfig] = {
    # The env's original model, kept bit for bit: an unbiased fix every second with
    # sigma = 0.15 m + 3 % of the slant range on each axis, nothing else.
    "ideal": UsblConfig(
        preset="ideal", **{**_QUIET, "period_s": 1.0, "sigma_floor_m": 0.15, "sigma_per_m": 0.03}
    ),
    # A compact low-cost USBL, the Cerulean ROV Locator (Mk III class), from Cerulean Sonar's
    # documentation (docs.ceruleansonar.com "Accuracy expectations", the product's general
    # specification table on blog.ceruleansonar.com, and its 110 m slant-range test):
    #   update rate 1 Hz; angular resolution "typically 2 degrees" as a probable (50 %) error,
    #   i.e. sigma = 2 / 1.18 = 1.7 deg per axis; heading reference error 3-5 deg probable with a
    #   magnetic compass (0.5 deg with a GNSS compass): 4 deg; slant range resolution 0.1 m and
    #   about 0.5 m error at 110 m (partly multipath): 0.05 m + 0.45 % of range.
    # Nominal: tilt misalignment 1 deg, sound-speed scale 1 % (a unit set for 1500 m/s in a
    # fresh-water tank at about 1480 m/s), range offset 0.1 m (the documented clock drift of
    # 2 m/h, three minutes after a sync), 5 % multipath outliers of 0.5 m, 10 % lost fixes,
    # 0.2 s processing latency.
    "cerulean-rovl": UsblConfig(
        preset="cerulean-rovl",
        period_s=1.0,
        sigma_floor_m=0.0,
        sigma_per_m=0.0,
        range_sigma_m=0.05,
        range_sigma_per_m=0.0045,
        bearing_sigma_deg=1.7,
        tilt_bias_sigma_deg=1.0,
        heading_bias_sigma_deg=4.0,
        range_scale_sigma_rel=0.01,
        range_offset_sigma_m=0.1,
        outlier_prob=0.05,
        outlier_sigma_m=0.5,
        dropout_prob=0.1,
        latency_s=0.2,
    ),
    # An acoustic-modem USBL, the EvoLogics S2C R 18/34 USBL the Girona 500 AUV carries, used as
    # the IQUA Robotics COLA2 stack uses it: the surface transceiver fixes the vehicle and sends
    # the fix down in the *next* acoustic message (COLA2 "comms" wiki), so a fix is one message
    # cycle old when it arrives. EvoLogics quotes a positioning accuracy (Drms) below 0.1 % of
    # the slant range: 0.1 % of range along and 0.06 deg (1 mrad) across the line of sight.
    # Nominal: message cycle 2 s (latency 2 s), 1 cm range floor, a calibrated installation
    # (0.5 deg tilt, 0.5 deg heading: the GNSS-compass figure above), sound-speed scale 0.5 %,
    # 2 % outliers of 1 m, 20 % lost messages.
    "evologics-s2cr": UsblConfig(
        preset="evologics-s2cr",
        period_s=2.0,
        sigma_floor_m=0.0,
        sigma_per_m=0.0,
        range_sigma_m=0.01,
        range_sigma_per_m=0.001,
        bearing_sigma_deg=0.06,
        tilt_bias_sigma_deg=0.5,
        heading_bias_sigma_deg=0.5,
        range_scale_sigma_rel=0.005,
        range_offset_sigma_m=0.0,
        outlier_prob=0.02,
        outlier_sigma_m=1.0,
        dropout_prob=0.2,
        latency_s=2.0,
    ),
}


@dataclass(frozen=True)
class UsblFix:
    """One acoustic fix as the vehicle receives it.

    Attributes:
        p_world_ds_m: (3,) the DS position the fix gives (world NED, m).
        sigma_m: its standard deviation on each axis, as the filter is told (m).
        ping_time_s: simulated time of the geometry it describes (s).
        outlier: the fix is a multipath outlier (ground truth, for diagnostics).
    """

    p_world_ds_m: np.ndarray
    sigma_m: float
    ping_time_s: float
    outlier: bool = False


def _across(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to the unit vector ``u`` and to each other."""
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(u)))] = 1.0
    e1 = cross3(u, helper)
    e1 /= math.sqrt(float(e1 @ e1))
    return e1, cross3(u, e1)


class UsblSensor:
    """A USBL transceiver on the vehicle fixing the DS transponder (module docstring).

    Args:
        cfg: the model; its unset fields are taken from its preset (:meth:`UsblConfig.resolved`).

    Raises:
        ValueError: a field outside its domain or an unknown preset (one line naming it).
    """

    def __init__(self, cfg: UsblConfig | None = None) -> None:
        cfg = (cfg or UsblConfig()).resolved()
        check_fields(cfg)
        self.cfg = cfg
        c = cfg
        self._iso = c.sigma_floor_m > 0 or c.sigma_per_m > 0
        self._geometric = any(
            v > 0
            for v in (
                c.range_sigma_m,
                c.range_sigma_per_m,
                c.bearing_sigma_deg,
                c.tilt_bias_sigma_deg,
                c.heading_bias_sigma_deg,
                c.range_scale_sigma_rel,
                c.range_offset_sigma_m,
            )
        )
        self.R_misalign = np.eye(3)
        self.range_scale = 1.0
        self.range_offset_m = 0.0
        self._history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._next_fix_s = -math.inf

    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: forget the poses and the schedule, draw this episode's bias
        (only the biases whose spread is non-zero draw)."""
        c = self.cfg
        tilt = math.radians(c.tilt_bias_sigma_deg)
        heading = math.radians(c.heading_bias_sigma_deg)
        roll, pitch = rng.normal(0.0, tilt, 2) if tilt > 0 else (0.0, 0.0)
        yaw = rng.normal(0.0, heading) if heading > 0 else 0.0
        self.R_misalign = R_from_rpy(float(roll), float(pitch), float(yaw))
        s = c.range_scale_sigma_rel
        self.range_scale = 1.0 + (float(rng.normal(0.0, s)) if s > 0 else 0.0)
        o = c.range_offset_sigma_m
        self.range_offset_m = float(rng.normal(0.0, o)) if o > 0 else 0.0
        self._history.clear()
        self._next_fix_s = -math.inf

    def sigma_m(self, slant_range_m: float) -> float:
        """Standard deviation of a fix on each axis at a slant range (m): noise and bias spreads
        together, the accuracy a datasheet quotes (outliers and latency excluded)."""
        c = self.cfg
        iso = c.sigma_floor_m + c.sigma_per_m * slant_range_m
        if not self._geometric:
            return iso
        angle = math.radians(
            math.hypot(c.bearing_sigma_deg, c.tilt_bias_sigma_deg, c.heading_bias_sigma_deg)
        )
        return math.hypot(
            iso,
            c.range_sigma_m + c.range_sigma_per_m * slant_range_m,
            slant_range_m * angle,
            slant_range_m * c.range_scale_sigma_rel,
            c.range_offset_sigma_m,
        )

    def fix(
        self,
        time_s: float,
        T_world_body: np.ndarray,
        p_world_ds_m: np.ndarray,
        rng: np.random.Generator,
    ) -> UsblFix | None:
        """The fix the vehicle receives at ``time_s``, or None (none due, or lost).

        Call it every control step: it keeps the vehicle's recent poses for the latency.

        Args:
            time_s: simulated time (s), non-decreasing within an episode.
            T_world_body: (4, 4) true vehicle pose (world NED, body FRD).
            p_world_ds_m: (3,) true DS (transponder) position (world NED, m).
            rng: the episode's random stream.
        """
        T_world_body = np.asarray(T_world_body, dtype=np.float64)
        if T_world_body.shape != (4, 4):  # a rigid transform, shape checked (called per step)
            raise ValueError(f"T_world_body: expected shape (4, 4), got {T_world_body.shape}")
        self._remember(time_s, T_world_body)
        c = self.cfg
        if c.period_s <= 0 or time_s + _TIME_EPS_S < self._next_fix_s:
            return None
        self._next_fix_s += c.period_s
        if self._next_fix_s <= time_s + _TIME_EPS_S:  # the first fix, or the clock jumped
            self._next_fix_s = time_s + c.period_s
        if c.dropout_prob > 0 and rng.random() < c.dropout_prob:
            return None
        p_ds = np.array(p_world_ds_m, dtype=np.float64)
        ping_s = time_s - c.latency_s if c.latency_s > 0 else time_s
        p_ping, R_ping = self._pose_at(ping_s) if c.latency_s > 0 else self._history[-1][1:]
        r = float(np.linalg.norm(p_ds - p_ping))
        sigma = self.sigma_m(r)
        fix = p_ds
        if c.latency_s > 0:  # placed with the position now, not the one at the ping
            fix = fix + (T_world_body[:3, 3] - p_ping)
        if self._geometric:
            fix = fix + self._geometric_error(p_ds - p_ping, R_ping, rng)
        outlier = c.outlier_prob > 0 and bool(rng.random() < c.outlier_prob)
        if outlier:
            fix = fix + rng.normal(0.0, c.outlier_sigma_m, 3)
        if self._iso:
            fix = fix + rng.normal(0.0, c.sigma_floor_m + c.sigma_per_m * r, 3)
        return UsblFix(fix, sigma, ping_s, outlier)

    # ------------------------------------------------------------------ internals
    def _geometric_error(
        self, rel_world_m: np.ndarray, R_world_body: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """(3,) error (world, m) of the measured DS position relative to the vehicle: range and
        bearing noise, misalignment, range scale and offset, in the transceiver's frame."""
        c = self.cfg
        d_body = R_world_body.T @ rel_world_m
        r = float(np.linalg.norm(d_body))
        if r < 1e-9:
            return np.zeros(3)
        u = self.R_misalign @ (d_body / r)
        if c.bearing_sigma_deg > 0:
            a, b = rng.normal(0.0, math.radians(c.bearing_sigma_deg), 2)
            e1, e2 = _across(u)
            w = a * e1 + b * e2  # rotation vector across the line of sight
            angle = float(np.linalg.norm(w))
            if angle > 0:
                u = u * math.cos(angle) + cross3(w / angle, u) * math.sin(angle)
        r_meas = r * self.range_scale + self.range_offset_m
        range_sigma = c.range_sigma_m + c.range_sigma_per_m * r
        if range_sigma > 0:
            r_meas += float(rng.normal(0.0, range_sigma))
        return R_world_body @ (r_meas * u) - rel_world_m

    def _remember(self, time_s: float, T_world_body: np.ndarray) -> None:
        """Keep the pose at ``time_s`` and drop those older than the latency needs."""
        h = self._history
        if h and time_s < h[-1][0] - _TIME_EPS_S:
            raise ValueError(
                f"time_s: {time_s:g} s is before the last call ({h[-1][0]:g} s); "
                "reset the sensor between episodes"
            )
        h.append((float(time_s), T_world_body[:3, 3].copy(), T_world_body[:3, :3].copy()))
        oldest_needed_s = time_s - self.cfg.latency_s
        while len(h) >= 2 and h[1][0] <= oldest_needed_s + _TIME_EPS_S:
            h.popleft()

    def _pose_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Vehicle position (linear between the kept poses) and attitude (the nearer kept one)
        at ``t_s``; before the first kept pose, that pose (the vehicle waited at its spawn)."""
        h = self._history
        t0, p0, R0 = h[0]
        if t_s <= t0 + _TIME_EPS_S:
            return p0, R0
        for (ta, pa, Ra), (tb, pb, Rb) in zip(h, list(h)[1:], strict=False):
            if abs(tb - t_s) <= _TIME_EPS_S:
                return pb, Rb
            if ta < t_s < tb:
                w = (t_s - ta) / (tb - ta)
                return pa + w * (pb - pa), (Ra if w < 0.5 else Rb)
        return h[-1][1], h[-1][2]
