"""The verification plan: mesh, passes, approach directions, tool offsets, timing (Eq. 4).

A :class:`Plan` holds, per measured point (internal units): the mesh point
index, the run (pass), the time, the nominal axis positions, the approach
direction of each axis, the tool offset and the temperature of every sensor.
Recordings and simulations share it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError
from .machine import AXES, AXIS_INDEX, is_rotary

T20 = 293.15  # K


@dataclass
class Sensor:
    """A temperature sensor column and what it is attached to."""

    column: str
    attached_to: str  # "x axis", "y axis", "z axis" or "air"
    position: float | None = None  # mm along its axis (for interpolation); None = whole axis

    @property
    def axis(self) -> str | None:
        s = self.attached_to.strip().lower()
        return s[0] if s in ("x axis", "y axis", "z axis") else None


@dataclass(frozen=True)
class Scale:
    """The nominal thermal behaviour of an axis scale, for the correction to the reference temperature.

    At the axis temperature T the scale reads the nominal position p while the axis is at
    ``fixed_point + (p - fixed_point) * (1 + cte * (T - T_ref))`` (the paper's Eq. 7-9 with the
    scale's fixed point instead of the axis zero).  ``cte`` in 1/K, ``fixed_point`` in mm.
    """

    cte: float
    fixed_point: float = 0.0


@dataclass
class Plan:
    point: np.ndarray  # (M,) int
    run: np.ndarray  # (M,) int
    time: np.ndarray  # (M,) s
    nominal: np.ndarray  # (M, 3) mm
    direction: np.ndarray  # (M, 3) +1/-1
    tool: np.ndarray  # (M, 3) mm
    temperature: dict = field(default_factory=dict)  # column -> (M,) K
    sensors: list = field(default_factory=list)
    scales: dict = field(default_factory=dict)  # axis -> Scale: the nominal expansion to correct (none: no correction)
    # five-axis machines: the commanded angle of each rotary axis (letter -> (M,) rad), the direction from which it
    # last approached it (letter -> (M,) +1/-1) and its nominal geometry (letter -> machine.RotaryAxis)
    angles: dict = field(default_factory=dict)
    angle_direction: dict = field(default_factory=dict)
    rotary: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.point)

    def direction_of(self, axis: str) -> np.ndarray:
        """The approach direction (+1/-1) of a linear or rotary axis at every point."""
        if is_rotary(axis):
            return np.asarray(self.angle_direction.get(axis, np.ones(len(self))), float)
        return self.direction[:, AXIS_INDEX[axis]]

    def axis_temperature(self, axis: str, reference: float = T20) -> np.ndarray:
        """Temperature of an axis at each point (K).

        Sensors attached to the axis with a ``position`` are interpolated
        linearly along the axis (the paper's assumption); sensors without one
        are averaged.  With no sensor on the axis the reference is returned.
        """
        sens = [s for s in self.sensors if s.axis == axis and s.column in self.temperature]
        if not sens:
            return np.full(len(self), reference)
        placed = sorted([s for s in sens if s.position is not None], key=lambda s: s.position)
        if len(placed) >= 2:
            pos = self.nominal[:, AXIS_INDEX[axis]]
            xs = np.array([s.position for s in placed])
            T = np.stack([self.temperature[s.column] for s in placed], axis=1)  # (M, S)
            k = np.clip(np.searchsorted(xs, pos) - 1, 0, len(xs) - 2)
            f = np.clip((pos - xs[k]) / (xs[k + 1] - xs[k]), 0.0, 1.0)
            rows = np.arange(len(self))
            return T[rows, k] * (1 - f) + T[rows, k + 1] * f
        return np.mean([self.temperature[s.column] for s in sens], axis=0)

    def subset(self, mask) -> "Plan":
        return Plan(
            self.point[mask], self.run[mask], self.time[mask], self.nominal[mask], self.direction[mask],
            self.tool[mask], {k: v[mask] for k, v in self.temperature.items()}, list(self.sensors),
            dict(self.scales), {k: v[mask] for k, v in self.angles.items()},
            {k: v[mask] for k, v in self.angle_direction.items()}, dict(self.rotary),
        )

    def nominal_expansion(self, reference: float = T20) -> dict:
        """The known expansion of the stated scales as fixed model inputs (``identify(..., fixed=...)``): applied in
        the identification, the geometric errors it returns are those of the machine at the reference temperature.
        Empty when no scale is stated (no correction).  See :meth:`expansion`."""
        return self.expansion(self.scales, reference)

    def expansion(self, scales: dict, reference: float = T20) -> dict:
        """Model inputs of scales ``{axis: Scale}`` expanding with their axis temperature: (M,) arrays.

        ``axis_scale.<a>`` = cte (T_a - T_ref) and ``axis_offset.<a>`` = -fixed_point s / (1 + s), so that the
        chain's effective position ``(p + offset) (1 + scale)`` is ``fixed_point + (p - fixed_point) (1 + s)``.
        """
        out = {}
        for axis, sc in sorted(scales.items()):
            s = sc.cte * (self.axis_temperature(axis, reference) - reference)
            out[f"axis_scale.{axis}"] = s
            if sc.fixed_point:
                out[f"axis_offset.{axis}"] = -sc.fixed_point * s / (1.0 + s)
        return out


def mesh(ranges: dict, step: dict | float) -> np.ndarray:
    """Grid of nominal positions, x fastest (the recordings' order): (M, 3)."""
    axes = []
    for a in AXES:
        lo, hi = ranges[a]
        st = step[a] if isinstance(step, dict) else step
        if st <= 0:
            raise ConfigError(f"mesh step of axis {a} must be positive, got {st} mm")
        n = int(round((hi - lo) / st)) + 1
        if n < 1 or abs(lo + (n - 1) * st - hi) > 1e-6 * max(1.0, abs(hi)):
            raise ConfigError(f"mesh axis {a}: range {lo}..{hi} mm is not a whole number of {st} mm steps")
        axes.append(lo + st * np.arange(n))
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)


def build_plan(
    points: np.ndarray,
    tools: list,
    runs: int = 2,
    feed: float = 2000.0 / 60.0,
    stop_time: float = 12.0,
    tool_change_time: float = 120.0,
    start_direction: float = 1.0,
    rotary: dict | None = None,
) -> Plan:
    """Sequence the mesh into passes and time it with Eq. 4.

    Each run visits every point once per tool offset; even runs go through
    the mesh in reverse order (passes alternate direction).  The time of the
    i-th measurement is ``L_T(i)/F + T_s * i`` (Eq. 4, ``L_T`` the path length
    travelled so far) plus a tool-change time between tool offsets.  The
    approach direction of an axis is the sign of its last move (it keeps the
    previous sign when the axis does not move); it starts at
    ``start_direction``.

    Five-axis machines: ``points`` (M0, 3 + R) carries the commanded angles (rad) of the rotary axes of
    ``rotary`` ({letter: machine.RotaryAxis}, in the order a, b, c) after x, y, z; a rotary move costs the stop
    time only (its angular feed is not modelled), and its approach direction is the sign of its last move.
    """
    points = np.asarray(points, float)
    letters = sorted(rotary or {})
    if points.ndim != 2 or points.shape[1] != 3 + len(letters):
        raise ConfigError(f"plan points must have 3 + {len(letters)} columns (x, y, z and the rotary axes' angles), "
                          f"got shape {points.shape}")
    if feed <= 0 or stop_time < 0:
        raise ConfigError("feed must be > 0 and stop time >= 0")
    M0 = len(points)
    rows_point, rows_run, rows_tool = [], [], []
    for r in range(1, runs + 1):
        order = np.arange(M0) if r % 2 == 1 else np.arange(M0)[::-1]
        for tool in tools:
            rows_point.append(order)
            rows_run.append(np.full(M0, r))
            rows_tool.append(np.tile(np.asarray(tool, float), (M0, 1)))
    point = np.concatenate(rows_point)
    run = np.concatenate(rows_run)
    tool = np.concatenate(rows_tool)
    full = points[point]
    nominal = np.ascontiguousarray(full[:, :3])
    M = len(point)
    time = np.zeros(M)
    direction = np.zeros((M, full.shape[1]))
    last_dir = np.full(full.shape[1], float(start_direction))
    t = 0.0
    for i in range(M):
        if i > 0:
            move = full[i] - full[i - 1]
            t += np.linalg.norm(move[:3]) / feed + stop_time
            if np.any(tool[i] != tool[i - 1]):
                t += tool_change_time
            nz = move != 0
            last_dir[nz] = np.sign(move[nz])
        time[i] = t
        direction[i] = last_dir
    angles = {r: np.ascontiguousarray(full[:, 3 + k]) for k, r in enumerate(letters)}
    angle_direction = {r: np.ascontiguousarray(direction[:, 3 + k]) for k, r in enumerate(letters)}
    return Plan(point.astype(int), run.astype(int), time, nominal, np.ascontiguousarray(direction[:, :3]), tool,
                angles=angles, angle_direction=angle_direction, rotary=dict(rotary or {}))


def verification_time(path_length: float, feed: float, stop_time: float, n: int) -> float:
    """Eq. 4: ``T_v = L_T / F + T_s (n - 1)``."""
    return path_length / feed + stop_time * (n - 1)
