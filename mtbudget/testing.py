"""Calibrate a diagnosis candidate: simulated recordings with concealed effects, drawn by the one simulator.

For plugin authors (and mtbudget's own tests and benchmarks): every case is
drawn from a seed — a machine with random geometric errors, a tracker at a
random pose, drifting temperatures with an air-conditioning cycle, the
tracker and machine noise of the example recordings — and, optionally, one
or two effects at a chosen multiple of the point noise.  The effects are the
opt-in *sources* of the simulated physics (``thermal_expansion``,
``reversal``, ``tracker_drift``, ``tracker_range_offset``, ``axis_coupling``,
``air_temperature_drift``), so a case is simulated by exactly the code that
simulates every other verification, and independently of the candidates'
own refit.  The recordings go through the same writer and reader as real
ones (optionally in inch, minutes and degF), so the diagnosis sees exactly
what a shop would send::

    from mtbudget.testing import run_case, named
    hits = sum(("my_effect", "x") in named(run_case(seed, (("my_effect", "x"),))[0]) for seed in range(100))

A candidate for an effect that has no simulating source yet needs one: write
it as an opt-in source in the same plugin and pass its settings with
``extra_sources``.

Beyond the library and beyond the stated noise: ``noise`` misstates the
uncertainties (``{"range": 4, "transverse": 2, "repeatability": 3}`` simulates
that much more noise than the recording states), and the effects
``spindle_thermal_growth``, ``column_tilt``, ``tool_length_error``, ``axis_polynomial`` (axis
``"xy2"``: a z error in x y^2; ``"xyz"``: an x error in x y z, outside every
candidate) are drawn by the opt-in sources of plugins/machine_tool.py, written
independently of the candidates.  :data:`EXPECTED` maps each to the candidate
that should name it (None: outside the library).  Effects that follow a
temperature are drawn with a physically plausible parameter: when the test's
temperature change is too small for the effect to reach its multiple of the
noise with one, the sensor's drift is made larger.
"""

from __future__ import annotations

import copy
import math
import tempfile
from pathlib import Path

import numpy as np

from .config import SimulationConfig, parse_config
from .machine import AXIS_INDEX
from .recording import read_recording, write_recording
from .scenario import build_scenario
from .simulate import simulate_recording
from .units import Q_, display

BASE = {
    "format": "mtbudget-config/1", "name": "calibration", "machine": "XFYZ", "seed": 1,
    "mesh": {"x": ["800 mm", "1200 mm"], "y": ["100 mm", "500 mm"], "z": ["200 mm", "400 mm"], "step": "100 mm"},
    "plan": {"runs": 2, "tools": [["0 mm", "0 mm", "-150 mm"], ["0 mm", "0 mm", "-300 mm"]], "feed": "2000 mm/min",
             "stop_time": "12 s", "tool_change_time": "120 s"},
    "tracker": {"D": "-800 mm", "L": "200 mm", "H": "650 mm", "a": "0 rad", "b": "0 rad", "d": "0.3 rad",
                "angular": "5 urad", "distance": "4 um", "distance_per_length": "0.8 um/m"},
    "machine_tool": {"repeatability": "1.5 um", "max_degree": 3},
    "geometric_errors": {"seed": 1, "translational": ["8 um", "3 um", "1.5 um"], "angular": ["12 urad", "5 urad", "2.5 urad"],
                         "squareness": "30 urad"},
    # the noise a recording states is the noise it has: tracker noise at its stated angular value, and repeatability
    "sources": {"enable": ["tracker_noise", "repeatability"], "tracker_noise": {"angular_sd": "0 urad"}},
}
EFFECTS = ("thermal_expansion", "reversal", "tracker_drift", "tracker_range_offset", "axis_coupling", "air_temperature_drift",
           "spindle_growth", "column_tilt", "tool_length", "axis_polynomial")
#: (effect, axis) of a case -> the (effect, axis) a diagnosis should name, None when no candidate describes it
EXPECTED = {("spindle_growth", None): ("spindle_growth", None), ("tool_length", None): ("tool_length", None),
            ("column_tilt", "x"): ("column_tilt", "x"), ("column_tilt", "y"): ("column_tilt", "y"),
            ("axis_polynomial", "xy2"): ("axis_coupling_quadratic", "xy"), ("axis_polynomial", "xyz"): None}
#: the largest parameter drawn for effects that follow a temperature (the plausible ranges are wider)
PLAUSIBLE_DRAW = {"thermal_expansion": 20.0, "spindle_growth": 30.0, "column_tilt": 30.0}  # um/(m*K), um/K, urad/K


def expected(effect) -> tuple | None:
    """The (effect, axis) a diagnosis should name for a concealed ``effect`` (None: outside the library)."""
    return EXPECTED.get(tuple(effect), tuple(effect))


def case_config(seed: int, effects: tuple = (), multiple: float = 2.5, noise: dict | None = None
                ) -> tuple[SimulationConfig, dict]:
    """A random verification with ``effects`` ((name, axis) pairs) at ``multiple`` x the point noise.

    ``noise``: factors by which the simulated noise exceeds the stated one ("range", "transverse",
    "repeatability"); :func:`simulate_case` states the unscaled values.
    Returns the config and the truth of the effects in display units.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7919]))
    raw = copy.deepcopy(BASE)
    raw["seed"] = int(seed)
    raw["geometric_errors"]["seed"] = int(seed) + 1000
    t = raw["tracker"]
    t["D"] = f"{rng.uniform(-1100, -550):.3f} mm"
    t["L"] = f"{rng.uniform(-100, 500):.3f} mm"
    t["H"] = f"{rng.uniform(500, 800):.3f} mm"
    t["a"], t["b"] = f"{rng.normal(0, 0.003):.6f} rad", f"{rng.normal(0, 0.003):.6f} rad"
    t["d"] = f"{rng.uniform(-0.45, 0.45):.6f} rad"
    raw["sensors"] = []
    for col, att in (("T_x", "x axis"), ("T_y", "y axis"), ("T_z", "z axis"), ("T_air", "air")):
        # a slow drift, the air conditioning's cycle (stronger in the air than in the structure), reading noise
        cyc = rng.uniform(0.08, 0.2) if att == "air" else rng.uniform(0.0, 0.04)
        raw["sensors"].append({"column": col, "attached_to": att, "start": f"{rng.uniform(19.8, 20.8):.3f} degC",
                               "rate": f"{rng.choice([-1, 1]) * rng.uniform(0.25, 0.6):.3f} K/h",
                               "noise": "0.015 K", "cycle_amplitude": f"{cyc:.3f} K",
                               "cycle_period": f"{rng.uniform(15, 40):.1f} min", "cycle_phase": f"{rng.uniform(0, 6.28):.3f} rad"})
    cfg = parse_config(raw)
    sigma = point_noise(cfg)
    plan = cfg.plan(np.random.default_rng(np.random.SeedSequence(cfg.seed)))
    # effects that follow a temperature: a plausible parameter, the sensor drifting faster where needed
    for name, axis in effects:
        if name in PLAUSIBLE_DRAW:
            col = f"T_{axis}" if name == "thermal_expansion" else "T_z"
            for _ in range(8):
                need = _sensor_effect_parameter(name, axis, plan, cfg, multiple * sigma)
                if need <= PLAUSIBLE_DRAW[name]:
                    break
                sen = next(x for x in raw["sensors"] if x["column"] == col)
                rate = float(sen["rate"].split()[0]) * min(need / PLAUSIBLE_DRAW[name] * 1.1, 4.0)
                sen["rate"] = f"{rate:.4f} K/h"
                cfg = parse_config(raw)
                plan = cfg.plan(np.random.default_rng(np.random.SeedSequence(cfg.seed)))
    truth: dict = {}
    settings: dict = {}

    def put(source, param, quantity):
        settings.setdefault(source, {})[param] = quantity

    for name, axis in effects:
        amp = multiple * sigma
        sign = None
        if name == "thermal_expansion":
            i = AXIS_INDEX[axis]
            dT = plan.axis_temperature(axis, cfg.reference_temperature) - cfg.reference_temperature
            cte = amp / np.ptp(plan.nominal[:, i] * dT)  # the effect spans amp over the test
            put(name, f"cte_{axis}", _q(display(cte, '1/K', 'um/(m*K)'), "um/(m*K)"))
            truth[(name, axis)] = display(cte, "1/K", "um/(m*K)")
        elif name == "reversal":
            put(name, f"B_{axis}", _q(display(amp, 'mm', 'um'), "um"))
            truth[(name, axis)] = display(amp, "mm", "um")
        elif name == "tracker_drift":
            v = rng.normal(0, 1, 3)
            v = v / np.linalg.norm(v) * amp / plan.time[-1]
            for a, va in zip("xyz", v):
                put(name, f"v_{a}", _q(display(va, 'mm/s', 'um/h'), "um/h"))
            truth[(name, None)] = display(v, "mm/s", "um/h").tolist()
        elif name == "tracker_range_offset":
            sign = rng.choice([-1, 1])
            put(name, "offset", _q(display(amp * sign, 'mm', 'um'), "um"))
        elif name == "axis_coupling":
            sign = rng.choice([-1, 1])
            put(name, axis, _q(display(amp * sign, 'mm', 'um'), "um"))
        elif name == "air_temperature_drift":
            sign = rng.choice([-1, 1])
            T = np.mean([plan.temperature[s.sensor.column] for s in cfg.sensors if s.sensor.attached_to == "air"], axis=0)
            put(name, "sensitivity", _q(display(amp * sign / np.ptp(T), 'mm/K', 'um/K'), "um/K"))
        elif name == "spindle_growth":
            g = _sensor_effect_parameter(name, axis, plan, cfg, amp)
            put("spindle_thermal_growth", "growth", _q(g, "um/K"))
            put("spindle_thermal_growth", "sensor", "T_z")
            truth[(name, axis)] = g
        elif name == "column_tilt":
            tilt = _sensor_effect_parameter(name, axis, plan, cfg, amp) * rng.choice([-1, 1])
            put(name, f"tilt_{axis}", _q(tilt, "urad/K"))
            put(name, "sensor", "T_z")
            truth[(name, axis)] = tilt
        elif name == "tool_length":
            sign = rng.choice([-1, 1])
            put("tool_length_error", "error", _q(display(amp * sign, 'mm', 'um'), "um"))
            put("tool_length_error", "tool", "2")
        elif name == "axis_polynomial":
            sign = rng.choice([-1, 1])
            powers, direction = {"xy2": ((1, 2, 0), "z"), "xyz": ((1, 1, 1), "x")}[axis]
            put(name, "amplitude", _q(display(amp * sign, 'mm', 'um'), "um"))
            put(name, "direction", direction)
            for a, pw in zip("xyz", powers):
                put(name, f"p{a}", str(pw))
        else:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
        if sign is not None:
            truth[(name, axis)] = display(amp * sign, "mm", "um")
    for key, f in (noise or {}).items():  # simulate more noise than the recording will state
        if key == "range":
            for k in ("distance", "distance_per_length"):
                v, u = raw["tracker"][k].split(maxsplit=1)
                raw["tracker"][k] = f"{float(v) * f!r} {u}"
        elif key == "transverse":
            v, u = raw["tracker"]["angular"].split(maxsplit=1)
            raw["tracker"]["angular"] = f"{float(v) * f!r} {u}"
        elif key == "repeatability":
            v, u = raw["machine_tool"]["repeatability"].split(maxsplit=1)
            raw["machine_tool"]["repeatability"] = f"{float(v) * f!r} {u}"
        else:
            raise ValueError(f"unknown noise component {key!r}; known: range, transverse, repeatability")
    if settings:
        raw["sources"]["enable"] = BASE["sources"]["enable"] + list(settings)
        raw["sources"].update(settings)
    if settings or noise:
        cfg = parse_config(raw)
    if noise:
        cfg.stated_noise_factors = dict(noise)
    return cfg, truth


def _sensor_effect_parameter(name, axis, plan, cfg, amp):
    """The parameter (display units) an effect that follows a temperature needs to span ``amp`` (mm)."""
    if name == "thermal_expansion":
        i = AXIS_INDEX[axis]
        dT = plan.axis_temperature(axis, cfg.reference_temperature) - cfg.reference_temperature
        return display(amp / np.ptp(plan.nominal[:, i] * dT), "1/K", "um/(m*K)")
    T = plan.temperature["T_z"]
    dT = T - T[0]
    if name == "spindle_growth":
        return display(amp / np.ptp(dT), "mm/K", "um/K")
    height = plan.nominal[:, 2] + plan.tool[:, 2]
    return display(amp / np.ptp(dT * height), "1/K", "urad/K")


def _q(value, unit: str) -> str:
    """A quantity string for a configuration, with every digit of ``value``."""
    return f"{float(value)!r} {unit}"


def point_noise(cfg: SimulationConfig) -> float:
    """Typical standard deviation of one measured coordinate (mm): tracker transverse and range, and repeatability."""
    r = math.sqrt(cfg.pose[0] ** 2 + cfg.pose[2] ** 2) + 1000.0
    ua, ur = cfg.angular * r, cfg.distance + cfg.distance_per_length * r
    return math.sqrt((2 * ua**2 + ur**2) / 3 + cfg.repeatability**2)


def simulate_case(cfg: SimulationConfig, folder: Path, imperial: bool = False):
    """Simulate the case (one engine trial of its scenario), write it as a recording and read it back.

    A case drawn with misstated noise states the noise divided by its factors (what the shop believed)."""
    rec, truth = simulate_recording(build_scenario(cfg))
    for key, f in getattr(cfg, "stated_noise_factors", {}).items():
        if key == "range":
            rec.distance, rec.distance_per_length = rec.distance / f, rec.distance_per_length / f
        elif key == "transverse":
            rec.angular = rec.angular / f
        else:
            rec.repeatability = rec.repeatability / f
    write_recording(rec, folder, truth=truth)
    if imperial:
        _to_imperial(folder)
    return read_recording(folder)


def _to_imperial(folder: Path):
    p = folder / "points.csv"
    lines = p.read_text().splitlines()
    head = lines[0].split(",")
    conv = []
    for h in head:
        if h.endswith("[mm]"):
            conv.append((h.replace("[mm]", "[in]"), lambda v: f"{display(float(v), 'mm', 'inch'):.9f}"))
        elif h.endswith("[s]"):
            conv.append((h.replace("[s]", "[min]"), lambda v: f"{display(float(v), 's', 'min'):.8f}"))
        elif h.endswith("[degC]"):
            conv.append((h.replace("[degC]", "[degF]"), lambda v: f"{Q_(float(v), 'degC').to('degF').magnitude:.6f}"))
        else:
            conv.append((h, lambda v: v))
    out = [",".join(c[0] for c in conv)]
    for line in lines[1:]:
        out.append(",".join(f(v) for (_, f), v in zip(conv, line.split(","))))
    p.write_text("\n".join(out) + "\n")


def run_case(seed: int, effects: tuple = (), multiple: float = 2.5, imperial: bool = False, candidates=None,
             noise: dict | None = None):
    """Simulate one case and diagnose it: (diagnosis, truth)."""
    from .diagnose import diagnose

    cfg, truth = case_config(seed, effects, multiple, noise)
    with tempfile.TemporaryDirectory() as tmp:
        rec = simulate_case(cfg, Path(tmp) / "rec", imperial)
        return diagnose(rec, candidates), truth


def named(diag) -> set:
    """The effects a diagnosis names outright."""
    return {(f.candidate.effect, f.candidate.axis) for f in diag.findings}


def explained(diag) -> bool:
    """Whether the diagnosis says the recording is explained (its fit gate passed)."""
    return diag.unexplained is None


def named_or_confounded(diag) -> set:
    """The effects a diagnosis names, with those it declares it cannot tell apart from them."""
    out = named(diag)
    for f in diag.findings:
        out |= {(c["effect"], c["axis"]) for c in f.confounded_with}
    return out


def named_alone(diag) -> set:
    """The effects a diagnosis names with no confounder: neither another candidate nor an explanation outside the
    library fits about as well."""
    return {(f.candidate.effect, f.candidate.axis) for f in diag.findings if f.named_alone}


def declared_outside(diag) -> set:
    """The effects a diagnosis names but declares confounded with an explanation outside the library."""
    return {(f.candidate.effect, f.candidate.axis) for f in diag.findings if f.outside}


def wrong_named(diag, want: set) -> set:
    """The findings that name a wrong effect (the counting rule of docs/diagnose.md, "Calibration beyond the library"):
    a finding that is not a hidden effect in ``want``, not declared confounded with one of them, and not declared
    confounded with an explanation outside the library (such a finding says "this, or something the library does not
    hold", which is not a wrong name).  In a recording with nothing hidden every finding is a false claim whatever it
    declares: count those with ``diag.findings``."""
    out = set()
    for f in diag.findings:
        key = (f.candidate.effect, f.candidate.axis)
        if key in want or f.outside or want & {(c["effect"], c["axis"]) for c in f.confounded_with}:
            continue
        out.add(key)
    return out
