"""The one simulator: sources drawn from their own streams, put through the truth model.

Every simulated measurement of mtbudget comes from :func:`simulate_block`:
the Monte Carlo engine's trials, ``mtbudget simulate`` (one engine trial
written as a recording, :func:`simulate_recording`), the diagnosis
calibration (:mod:`mtbudget.testing`) and ``replay --verify``.

Random streams: the numbers source ``s`` draws for block ``b`` of a run come
from ``SeedSequence(seed, spawn_key=(b, crc32(s.name)))``; they depend on the
seed, the block and the source only, never on which other sources are
active, how blocks are grouped, or where they run.
"""

from __future__ import annotations

import zlib

import numpy as np
import pint

from . import tracker as lt
from .contracts import Source, check_internal, check_sample, has_internal_sample, internal_unit
from .errors import PluginError
from .machine import COMPONENT_ERRORS
from .model import iso_parameter, parameter_from_iso
from .model import from_targets
from .plugins import call, caller
from .recording import Recording
from .scenario import Scenario, target_shapes
from .units import display


def stream(seed: int, block: int, source: Source) -> np.random.Generator:
    """The random stream of ``source`` in ``block`` of a run seeded ``seed``:
    ``default_rng(SeedSequence(seed, spawn_key=(block, crc32(source.name))))``."""
    return streams(seed, block, (source,))[0]


def streams(seed: int, block: int, sources) -> list:
    """:func:`stream` of each of ``sources`` in ``block``: the same generators, state for state, at a tenth of the
    cost of a ``SeedSequence`` each.

    numpy's ``SeedSequence(seed, spawn_key=(block, crc))`` hashes its entropy words (the seed's, padded to the pool
    of four, then the block's, then the crc's) into a pool of four words, and ``PCG64`` seeds itself with the eight
    words ``generate_state(4, uint64)`` makes of it (numpy/random/bit_generator.pyx, after O'Neill's seed_seq).
    Everything before the crc's word is the same for every source of a block (the seed's part remembered per seed,
    the block's word mixed in per block, in Python integers); the crc's word and ``generate_state`` are then a few
    uint32 operations on all the block's sources at once.  ``PCG64`` takes the words from a :class:`_Seeded` seed
    sequence, which is the numpy one in every other use (``spawn``, ``entropy``, other ``generate_state``
    requests).  The states are checked against numpy's own in tests/test_sampling_speed_streams.py; numpy
    guarantees both algorithms' stream compatibility."""
    seed, block = int(seed), int(block)
    if seed < 0 or block < 0:  # numpy's own error
        return [np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(block, _crc(s)))) for s in sources]
    pool, h = _prefix(seed, block)
    crcs, y = _crc_words(sources, h)
    p = pool - y  # mix: MIX_L * pool (pool holds it) - MIX_R * hashmix(crc), modulo 2^32
    p ^= p >> _XSHIFT
    w = p[:, _CYCLE]
    w ^= _STATE_HASH[:8]
    w *= _STATE_HASH[1:]
    w ^= w >> _XSHIFT
    words = w.astype("<u4", order="C").view("<u8").astype(np.uint64)  # generate_state's: little-endian pairs, native order
    Generator, PCG64 = np.random.Generator, np.random.PCG64
    return [Generator(PCG64(_Seeded(words[i], seed, block, c))) for i, c in enumerate(crcs)]


def _crc_words(sources, h: int) -> tuple:
    """(the sources' crc32s, ``MIX_R * hashmix(crc)`` for each crc and pool word (uint32 (S, 4))), the hash constants
    running on from ``h``: the same for every block whose number is one word (remembered per sources and ``h``)."""
    key = (tuple(s.name for s in sources), h)
    hit = _CRC_WORDS.get(key)
    if hit is None:
        crcs = [_crc(s) for s in sources]
        hc = _hash_constants(h, _MULT_A, 4)
        y = np.array(crcs, np.uint32)[:, None] ^ hc[:4]
        y *= hc[1:]
        y ^= y >> _XSHIFT
        y *= _MIX_R
        if len(_CRC_WORDS) > 64:
            _CRC_WORDS.clear()
        hit = _CRC_WORDS[key] = (crcs, y)
    return hit


_CRC_WORDS: dict = {}


def _crc(source) -> int:
    crc = _CRC.get(source.name)
    if crc is None:
        crc = _CRC[source.name] = zlib.crc32(source.name.encode())
    return crc


_CRC: dict = {}  # source name -> crc32 of its name

# numpy's SeedSequence (numpy/random/bit_generator.pyx): the hash constants, the pool of four uint32 words
_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R, _XSHIFT, _M32 = 0xCA01F9DD, 0x4973F715, 16, 0xFFFFFFFF
_CYCLE = np.array([0, 1, 2, 3, 0, 1, 2, 3])  # generate_state cycles through the pool


def _hash_constants(h: int, mult: int, k: int) -> np.ndarray:
    """h, h * mult, h * mult^2 ... (k + 1 values, uint32): the successive hash constants from ``h``."""
    out = [h]
    for _ in range(k):
        out.append(out[-1] * mult & _M32)
    return np.array(out, np.uint32)


_STATE_HASH = _hash_constants(_INIT_B, _MULT_B, 8)  # generate_state's, the same for every seed sequence


def _words(n: int) -> list:
    """An integer as uint32 words, lowest first (numpy's ``_int_to_uint32_array``: 0 is one word)."""
    out = [n & _M32]
    n >>= 32
    while n:
        out.append(n & _M32)
        n >>= 32
    return out


def _hashmix(v: int, h: int) -> tuple:
    """numpy's ``hashmix`` of ``v`` with the hash constant ``h``: (the hashed value, the next constant)."""
    v ^= h
    h = h * _MULT_A & _M32
    v = v * h & _M32
    return v ^ (v >> _XSHIFT), h


def _mix(x: int, y: int) -> int:
    r = (_MIX_L * x - _MIX_R * y) & _M32
    return r ^ (r >> _XSHIFT)


def _prefix(seed: int, block: int):
    """The pool after every entropy word but the crc's, as ``MIX_L * pool`` (uint32 (4,)), and the hash constant the
    crc's ``hashmix`` start from.  The seed's part (its words padded to the pool, mixed together) is
    remembered per seed; the block's words are mixed into it here."""
    hit = _PREFIX.get(seed)
    if hit is None:
        run = _words(seed)
        entropy = run + [0] * (4 - len(run))  # a spawn key pads the seed's words to the pool
        h = _INIT_A
        pool = []
        for v in entropy[:4]:
            v, h = _hashmix(v, h)
            pool.append(v)
        for i in range(4):
            for j in range(4):
                if i != j:
                    v, h = _hashmix(pool[i], h)
                    pool[j] = _mix(pool[j], v)
        for w in entropy[4:]:  # a seed of more than four words
            for j in range(4):
                v, h = _hashmix(w, h)
                pool[j] = _mix(pool[j], v)
        hit = (pool, h)
        if len(_PREFIX) > 64:
            _PREFIX.clear()
        _PREFIX[seed] = hit
    pool, h = list(hit[0]), hit[1]
    for w in _words(block):
        for j in range(4):
            v, h = _hashmix(w, h)
            pool[j] = _mix(pool[j], v)
    return np.array([_MIX_L * v & _M32 for v in pool], np.uint32), h


_PREFIX: dict = {}


class _Seeded(np.random.bit_generator.ISpawnableSeedSequence):
    """``SeedSequence(seed, spawn_key=(block, crc))`` whose ``generate_state(4, uint64)``, which ``PCG64`` asks once
    when it seeds itself, is already known (:func:`streams`); anything else is asked of the numpy seed sequence,
    made on first need, so ``spawn``, ``entropy``, ``spawn_key`` and the rest are numpy's."""

    __slots__ = ("_words", "_key", "_real")

    def __init__(self, words, seed, block, crc):
        self._words, self._key, self._real = words, (seed, block, crc), None

    def real(self) -> np.random.SeedSequence:
        if self._real is None:
            seed, block, crc = self._key
            self._real = np.random.SeedSequence(seed, spawn_key=(block, crc))
        return self._real

    def generate_state(self, n_words, dtype=np.uint32):
        words = self._words
        if words is not None and dtype is np.uint64 and n_words == 4:  # PCG64 seeding itself: once
            self._words = None
            return words
        return self.real().generate_state(n_words, dtype)

    def spawn(self, n_children):
        return self.real().spawn(n_children)

    def __getattr__(self, name):  # entropy, spawn_key, pool_size, n_children_spawned, state
        if name.startswith("__") or name in _Seeded.__slots__:
            raise AttributeError(name)
        return getattr(self.real(), name)

    def __reduce__(self):
        return _identity, (self.real(),)

    def __repr__(self):
        return repr(self.real())


def _identity(x):
    return x


def sample_source(scenario: Scenario, src: Source, n: int, rng: np.random.Generator, shapes: dict | None = None,
                  options: dict | None = None, invoke=call) -> dict:
    """``n`` trials of one source as internal float arrays, checked (keys, shapes, units, NaN, strategy indices).

    A source with ``sample_internal`` (the built-ins) gives float arrays in the internal units: no pint per block.
    options: a cache of each strategy source's options (source name -> list), filled on first use.
    invoke: :func:`mtbudget.plugins.call` or what :func:`mtbudget.plugins.caller` gave for a run of calls."""
    shapes = shapes or target_shapes(scenario)
    if has_internal_sample(src):
        arrays = check_internal(src, invoke(src, "sample_internal", n, rng, scenario.context), n, shapes)
    else:
        raw = invoke(src, "sample", n, rng, scenario.context)
        arrays = _as_internal(src, raw, n, shapes)
        if arrays is None:
            arrays = check_sample(src, raw, n, shapes)
    if "strategy" in arrays:
        if options is None or src.name not in options:
            opts = call(src, "options", scenario.context)
            if options is not None:
                options[src.name] = opts
        k = len(options[src.name] if options is not None else opts)
        s = arrays["strategy"]
        if s.size and not (np.minimum.reduce(s) >= 0 and np.maximum.reduce(s) < k and (s == np.floor(s)).all()):
            raise PluginError(f"'strategy' must hold option indices 0..{k - 1}", src.plugin, src.name,
                              "mtbudget_register_sources", "sample")
    return arrays


def _as_internal(src: Source, raw, n: int, shapes: dict) -> dict | None:
    """The sample as float arrays when every value is a Quantity already in its target's internal unit, of the
    right shape and finite (nothing to convert); None when anything needs :func:`mtbudget.contracts.check_sample`,
    which converts or says what is wrong."""
    if type(raw) is not dict:
        return None
    out = {}
    for key, q in raw.items():
        if key not in src.targets or not isinstance(q, pint.Quantity) or q.units != internal_unit(key):
            return None
        arr = np.asarray(q.magnitude, dtype=float)
        if arr.shape != (n,) + shapes[key] or not np.isfinite(arr).all():
            return None
        out[key] = arr
    return out


def simulate_block(scenario: Scenario, block: int, n: int, seed: int, active: list | None = None,
                   shapes: dict | None = None, options: dict | None = None, keep_draws: bool = False):
    """The simulated measurements of one block of ``n`` trials.

    Returns (measured tracker points (n, M, 3), true parameters (n, p),
    strategy choices [(source, option index per trial)]) for the ``active``
    sources (default: all the scenario's sources).  options: see :func:`sample_source`.
    keep_draws: keep each source's own arrays in ``draws`` [(source, {target: (n, ...) array})] (what
    :func:`truth_dict` asks the sources' ``drawn`` about); off in the engine (the arrays die with the block).
    """
    active = scenario.sources if active is None else active
    shapes = shapes or target_shapes(scenario)
    targets: dict = {}
    summed = set()  # targets whose array is a sum made here (added to in place; a source's own array never is)
    choices = []
    draws = [] if keep_draws else None
    invoke = caller()
    for src, rng in zip(active, streams(seed, block, active)):
        arr = sample_source(scenario, src, n, rng, shapes, options, invoke)
        if draws is not None:  # a source's own arrays are never added to in place (below)
            draws.append((src, arr))
        for k, v in arr.items():
            if k == "strategy":
                choices.append((src, v.astype(int)))
            elif k not in targets:
                targets[k] = v
            elif k in summed:
                targets[k] += v  # the same sums, in the same order, without a new array for each
            else:
                targets[k] = targets[k] + v
                summed.add(k)
    offset = targets.pop("measurand_offset", None)
    pert = scenario.truth_inputs(from_targets(targets))  # [scales]: the nominal expansion, about each fixed point
    truth = scenario.truth
    theta_true = scenario.theta[None, :] + pert.pop("geometry", 0.0)
    if theta_true.shape != (n, truth.n_params):
        theta_true = np.broadcast_to(theta_true, (n, truth.n_params))
    if scenario.stations:
        meas, ranges = measure_stations(scenario, truth.machine_points(theta_true, pert), pert)
    else:
        meas, ranges = truth.predict(theta_true, scenario.pose, pert), None
    out = SimulatedBlock((meas, theta_true, choices))
    out.measurand_offset = None if offset is None else np.broadcast_to(offset, (n, len(scenario.plan), 3))
    out.ranges = ranges
    out.pose_offset = _read_only(pert["pose"], (n, 6)) if "pose" in pert else None
    out.draws = draws
    return out


def _read_only(x: np.ndarray, shape: tuple) -> np.ndarray:
    """``np.broadcast_to(x, shape)`` (a read-only view), without its nditer when ``x`` has that shape already."""
    if x.shape != shape:
        return np.broadcast_to(x, shape)
    view = x.view()
    view.flags.writeable = False
    return view


def measure_stations(scenario: Scenario, P_W: np.ndarray, pert: dict):
    """What each station of [[stations]] measures of the machine points P_W (n, M, 3): an xyz station the point in
    its own frame (pose, spherical noise and offsets as one tracker, :meth:`mtbudget.model.MeasurementModel.predict`),
    a range station its distance plus the dead path.  The sources' tracker-frame perturbations (spherical noise,
    ``tracker_offset``) act on each row in its own station's frame; for a range station that frame is its position
    with no rotation, so the range noise adds to the range and an offset moves it by its component along the beam.

    Returns (xyz (n, M, 3) mm, NaN on range rows; ranges (n, M) mm, NaN on xyz rows).
    """
    n, M = P_W.shape[:2]
    xyz = np.full((n, M, 3), np.nan)
    ranges = np.full((n, M), np.nan)
    dpose = np.broadcast_to(pert.get("pose", np.zeros(6)), (n, 6))
    noise = pert.get("spherical_noise")
    offset = pert.get("tracker_offset")
    for st, spec in zip(scenario.stations, scenario.station_specs):
        rows = np.flatnonzero(scenario.row_station == st.id)
        if rows.size and rows[-1] - rows[0] + 1 == rows.size:  # the station's rows one after the other: views of
            rows = slice(rows[0], rows[-1] + 1)  # the arrays, not copies by fancy indexing (the same numbers)
        P = lt.read(P_W[:, rows], spec.tracker_pose[None] + dpose,
                    None if noise is None else np.broadcast_to(noise, (n, M, 3))[:, rows])
        if offset is not None:
            P += np.broadcast_to(offset, (n, M, 3))[:, rows]  # P is read's new array
        if st.kind == "xyz":
            xyz[:, rows] = P
        else:  # |P| summed in order (x^2 + y^2) + z^2, as numpy's sum over the last axis: the same bits
            ranges[:, rows] = lt.norm3(P) + spec.dead_path
    return xyz, ranges


class SimulatedBlock(tuple):
    """(measured tracker points, true parameters, strategy choices) of one block; ``measurand_offset``: (n, M, 3) mm,
    what sources add to the measurand only (the machine in use, what the verification cannot identify at another
    tool); None without such a source."""

    measurand_offset = None
    ranges = None  # (n, M) mm: the ranges of the range stations of [[stations]] (NaN on xyz rows); None without
    pose_offset = None  # (n, 6): what the sources drew on the tracker pose (every station moves by it); None without
    draws = None  # [(source, its arrays)] with simulate_block(keep_draws=True)


def simulate_recording(scenario: Scenario, seed: int | None = None, trial: int = 0, block: int = 64):
    """Trial ``trial`` of the engine's run seeded ``seed`` (default: the config's), as a recording and its truth."""
    cfg = scenario.config
    seed = cfg.seed if seed is None else int(seed)
    b, i = divmod(int(trial), int(block))
    sim = simulate_block(scenario, b, block, seed, keep_draws=True)
    noise = scenario.noise
    several = {}
    if scenario.stations:  # format 2: the station of every row, each station's stated uncertainties, the ranges
        several = {"station": np.array(scenario.row_station), "stations": list(scenario.stations),
                   "lt_range": sim.ranges[i].copy(), "format_version": 2}
    if scenario.plan.angles:  # a five-axis machine: format 3, the tracker's mount
        several = {**several, "format_version": 3, "mount": cfg.mount}
    rec = Recording(
        name=cfg.name, machine=cfg.machine, plan=scenario.plan, lt=sim[0][i].copy(), angular=noise.angular,
        distance=noise.distance, distance_per_length=noise.distance_per_length, repeatability=noise.repeatability,
        reference_temperature=cfg.reference_temperature,
        description=cfg.description or f"simulated by mtbudget (seed {seed}, trial {trial})", **several,
    )
    drawn = [(src, {k: v[i] for k, v in arr.items() if k != "strategy"}) for src, arr in sim.draws]
    return rec, truth_dict(scenario, seed, trial, None if sim.pose_offset is None else sim.pose_offset[i], sim[1][i],
                           drawn)


def _finite(x):
    """A float, or None where nothing drawn shows (NaN: JSON has no NaN)."""
    x = float(x)
    return x if np.isfinite(x) else None


def _add(a, b):
    return None if a is None or b is None else a + b


def drawn_dict(scenario: Scenario, draws) -> tuple[dict, dict]:
    """(``drawn``, ``diagnosable``) of truth.json from each source's arrays of one trial [(source, {target: array})]:
    what every source with a ``drawn`` method says it drew, and the sum per diagnosis candidate of the draws that
    are a physical effect a diagnosis can name (``effect``), with the sources it comes from."""
    drawn, named = {}, {}
    for src, arr in draws:
        if not callable(getattr(src, "drawn", None)):
            continue
        got = call(src, "drawn", arr, scenario.context) or {}
        if not isinstance(got, dict):
            raise PluginError("drawn must return a dict {name: {value, unit, meaning}}", src.plugin, src.name,
                              "mtbudget_register_sources", "drawn")
        out = {}
        for name, e in got.items():
            if not isinstance(e, dict) or not {"value", "unit", "meaning"} <= set(e):
                raise PluginError(f"drawn[{name!r}] must be a dict with value, unit and meaning", src.plugin,
                                  src.name, "mtbudget_register_sources", "drawn")
            v = e["value"]
            v = [_finite(x) for x in v] if isinstance(v, (list, tuple, np.ndarray)) else _finite(v)
            out[name] = {"value": v, "unit": str(e["unit"]), "meaning": str(e["meaning"]),
                         **({"effect": e["effect"]} if e.get("effect") else {})}
            label = e.get("effect")
            if label:
                acc = named.setdefault(label, {"value": 0.0 if not isinstance(v, list) else [0.0] * len(v),
                                               "unit": out[name]["unit"], "sources": []})
                if isinstance(acc["value"], list) != isinstance(v, list) or (
                        isinstance(v, list) and len(v) != len(acc["value"])):
                    raise PluginError(f"drawn[{name!r}]: {label} has another shape elsewhere (a value against a "
                                      "list, or lists of other lengths)", src.plugin, src.name,
                                      "mtbudget_register_sources", "drawn")
                if acc["unit"] != out[name]["unit"]:
                    raise PluginError(f"drawn[{name!r}]: {label} is in {acc['unit']} elsewhere, not "
                                      f"{out[name]['unit']}", src.plugin, src.name, "mtbudget_register_sources", "drawn")
                acc["value"] = ([_add(a, b) for a, b in zip(acc["value"], v)] if isinstance(v, list) else
                                _add(acc["value"], v))
                acc["sources"].append(f"{src.name}.{name}")
        drawn[src.name] = out
    return drawn, named


def truth_dict(scenario: Scenario, seed: int, trial: int, pose_offset: np.ndarray | None = None,
               theta: np.ndarray | None = None, draws: list | None = None) -> dict:
    """What a simulated recording holds, in display units (the ``truth.json`` beside it).  ``theta``: the geometric
    errors of the machine the trial measured (the configuration's machine plus what ``geometric_error_uncertainty``
    drew; default the configuration's): what ``compensate --check`` and a comparison with the identification need.
    ``draws``: each source's arrays of this trial [(source, {target: array})], for ``drawn`` and ``diagnosable``
    (:func:`drawn_dict`)."""
    model = scenario.truth
    coefs, sq = model.errors.coefficients(scenario.theta if theta is None else np.asarray(theta, float))
    rotary = {k: sq.pop(k) for k in list(sq) if k[3:4] in ("a", "b", "c") and "(" in k}  # five-axis: the rotary axes' terms, by name
    by_name = {s.name: s for s in scenario.sources}

    def fixed(name, pattern, unit):
        s = by_name.get(name)
        if s is None:
            return {}
        vals = {a: float(s.parameters[pattern.format(a)].to(unit).magnitude) for a in "xyz"}
        return {a: v for a, v in vals.items() if v}

    drift = fixed("tracker_drift", "v_{}", "um/h")
    dpose = np.zeros(6) if pose_offset is None else np.asarray(pose_offset, float)  # where the trial put the stations
    drawn, diagnosable = drawn_dict(scenario, draws) if draws is not None else ({}, {})
    return {
        "conventions": {
            "thermal": "axis -> CTE in um/(m K): the axis scale reads the nominal position p but moves to p * (1 + CTE * (T_axis - 20 degC)), about the axis zero"
                       + ("; on an axis of 'scales' about that scale's fixed point, on top of its nominal expansion" if scenario.plan.scales else ""),
            "scales": "axis -> the nominal expansion of its scale, stated in recording.toml [scales]: the simulated scale moves to fixed_point + (p - fixed_point) * (1 + cte * (T_axis - 20 degC)) at the true axis temperature (the reading plus what the sensor-calibration and drift sources drew), the identification corrects it at the read temperature",
            "reversal": "axis -> full reversal value B in um: approaching from either side the axis stops B/2 short of the target",
            "drift": "apparent velocity of the measured points in the machine frame, um/h, from the start of the test",
            "geometric_errors": "the machine this trial measured: the configuration's geometric errors plus what the "
                                "geometric_error_uncertainty source drew in this trial (the per-verification variation "
                                "of every coefficient, paper Eq. 18-20), as the Monte Carlo's measurand takes it",
            "effects": "the simulated physics the configuration enables (the opt-in sources thermal_expansion, reversal, tracker_drift), as configured; what the default sources drew in this trial is in 'drawn' and 'diagnosable'",
            "drawn": "source -> what it drew in this trial: name -> value in unit, with its meaning (the sources that say so; 'effect' names the diagnosis candidate it is)",
            "diagnosable": "diagnosis candidate label (reversal[x], thermal_expansion[x], tracker_drift, scale_following_time[x]: the x scale following time, thermal_expansion's declared alternative outside the library) -> the sum of what the sources drew of it in this trial, in the candidate's unit, and the sources; an effect a diagnosis can see only where the plan makes it visible and it exceeds the noise",
            "tracker_pose": "D, L, H in mm and Euler angles a, b, d in rad of the tracker frame in the machine frame (the paper's Eq. 21-22), as simulated (the configured pose plus what the registration source drew in this trial); with several stations, the first's",
            "stations": "with several stations, as simulated: each xyz station's pose as tracker_pose, each range station's position (mm, machine frame) and dead path (mm); the registration source moves every station by the same drawn offset",
        },
        "simulation": {"seed": int(seed), "trial": int(trial)},
        "drawn": drawn,
        "diagnosable": diagnosable,
        "effects": {
            "thermal": fixed("thermal_expansion", "cte_{}", "um/(m*K)"),
            "reversal": fixed("reversal", "B_{}", "um"),
            "drift": [drift.get(a, 0.0) for a in "xyz"] if drift else None,
        },
        "sources": {s.name: {k: (f"{v:~P}" if hasattr(v, "units") else str(v)) for k, v in s.parameters.items()}
                    for s in scenario.sources},
        "scales": {a: {"cte_um_per_m_K": display(sc.cte, "1/K", "um/(m*K)"), "fixed_point_mm": float(sc.fixed_point)}
                   for a, sc in sorted(scenario.plan.scales.items())},
        "tracker_pose": dict(zip("DLHabd", map(float, scenario.pose + dpose))),
        **({"stations": [{"id": st.id, "kind": st.kind, "description": st.description,
                          **({"pose": dict(zip("DLHabd", map(float, spec.pose + dpose)))} if st.kind == "xyz" else
                             {"position_mm": [float(v) for v in spec.position + dpose[:3]],
                              "dead_path_mm": float(spec.dead_path)})}
                         for st, spec in zip(scenario.stations, scenario.station_specs)]} if scenario.stations else {}),
        "noise": {"angular_urad": display(scenario.noise.angular, "rad", "urad"),
                  "dist_um": display(scenario.noise.distance, "mm", "um"),
                  "dist_ppm": display(scenario.noise.distance_per_length, "", "ppm"),
                  "repeat_um": display(scenario.noise.repeatability, "mm", "um")},
        "squareness_urad": {k: display(v, "rad", "urad") for k, v in sq.items()},
        **({"rotary_axes": {
            "convention": "each rotary axis' pivot (mm, machine frame with every axis at zero) and direction; its "
                          "location and zero errors by ISO 230-7 name (um for offsets, urad for orientation and zero "
                          "errors: rotations about +X, +Y, +Z) and any Fourier term of its error motions "
                          "(mtbudget name, e.g. dx(c)[c2], um or urad), in its carrier's frame (docs/model.md)",
            "geometry": {r.upper(): {"pivot_mm": list(map(float, ax.pivot)),
                                     "direction": f"{'+' if ax.sign > 0 else '-'}{'xyz'[ax.index]}"}
                         for r, ax in sorted(scenario.plan.rotary.items())},
            "errors": {(iso_parameter(k) if k.endswith("[O]") else k): display(v, "mm" if k[0] == "d" else "rad",
                                                                               "um" if k[0] == "d" else "urad")
                       for k, v in rotary.items()},
        }} if rotary or scenario.plan.rotary else {}),
        "geometric_errors": {
            "basis": "Legendre P1..Pn of the axis position normalised to [-1, 1] over the measured range; um for d*, urad for e*",
            "coefficients": {k: display(list(v), "mm" if k[0] == "d" else "rad", "um" if k[0] == "d" else "urad")
                             for k, v in coefs.items() if k in COMPONENT_ERRORS},
        },
    }


def parameters_from_truth(truth: dict, model) -> tuple[np.ndarray, np.ndarray, dict]:
    """(theta, pose, effects) in internal units from a ``truth.json`` dictionary."""
    co = {k: display(list(vs), "um" if k[0] == "d" else "urad", "mm" if k[0] == "d" else "rad")
          for k, vs in truth["geometric_errors"]["coefficients"].items()}
    named = {}
    for k, v in ((truth.get("rotary_axes") or {}).get("errors") or {}).items():  # five-axis: by ISO or mtbudget name
        name = parameter_from_iso(k) or k
        named[name] = display(v, "um" if name[0] == "d" else "urad", "mm" if name[0] == "d" else "rad")
    theta = model.errors.from_coefficients(co, {k: display(v, "urad", "rad") for k, v in truth.get("squareness_urad", {}).items()},
                                           {k: v for k, v in named.items() if k in model.errors.names})
    tp = truth["tracker_pose"]
    pose = np.array([tp[k] for k in "DLHabd"], float)
    e = truth.get("effects", {})
    effects = {
        "thermal": {a: display(v, "um/(m*K)", "1/K") for a, v in (e.get("thermal") or {}).items()},
        "reversal": {a: display(v, "um", "mm") for a, v in (e.get("reversal") or {}).items()},
        "drift": None if not e.get("drift") else display(np.asarray(e["drift"], float), "um/h", "mm/s"),
    }
    return theta, pose, effects


def truth_error_model(plan, degrees_from: dict, rotary_terms: dict | None = None):
    """An error model able to hold a truth.json (free convention, its degrees; a five-axis plan's rotary axes with
    as many Fourier terms as ``rotary_terms`` (truth.json's rotary_axes.errors) names)."""
    from .machine import ErrorModel

    base = ErrorModel.default(plan.nominal, straightness_convention="free")
    deg = {k: len(v) for k, v in degrees_from.items()}
    harmonics = {}
    for r in sorted(plan.angles):
        orders = [int(k.split("[")[1][1:-1]) for k in (rotary_terms or {}) if k[3:4] == r and "[" in k and
                  k.split("[")[1][:1] in "cs"]
        harmonics[r] = max(orders, default=0)
    return ErrorModel(ranges=base.ranges, degrees={**{k: 0 for k in base.degrees}, **deg}, straightness_convention="free",
                      rotary=harmonics)

