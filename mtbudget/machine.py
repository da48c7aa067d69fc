"""The one kinematic chain of a 3-axis machine tool (paper Eq. 1-2, 5-9, 15-20).

Configuration codes follow the paper: letters left of ``F`` move the
workpiece, letters right of it move the tool, and the letter next to ``F`` is
the axis mounted on the bed.  ``XFYZ`` (the paper's machine) has the X
carriage carrying the part, Y on the bed carrying Z, Z carrying the tool.

Conventions (all internal units: mm, rad):

* Each axis ``k`` is a carriage with a translation vector ``t_k`` and a
  rotation ``R_k`` (Eq. 6: ``R_k = I + [eps_k]x``, or the exact rotation
  ``expm([eps_k]x)`` when ``exact=True``).
* ``t_k = s_k * d_k + delta_k`` where ``s_k`` is +1 for tool-side axes and -1
  for workpiece-side axes, ``delta_k = (dx(k), dy(k), dz(k))`` are the carriage's
  own translational errors and ``d_k`` the commanded relative displacement
  including squareness: ``d_x = (p_x, 0, 0)``, ``d_y = (-p_y s_xy, p_y, 0)``,
  ``d_z = (-p_z s_xz, -p_z s_yz, p_z)`` (Eq. 7-9, 16-17).  X is the squareness
  reference.  For XFYZ this is exactly the paper's X, Y, Z vectors.
* ``p_k`` is the effective axis position: ``(p + offset) * (1 + scale)``
  (Eq. 15: backlash, repeatability and control add to the position, thermal
  expansion scales it about the axis zero).
* Tool point: ``P = A_1(A_2(...A_n(T)))`` over the tool-side axes, ``A(v) = R v + t``;
  workpiece frame: ``P_W = B_m^-1(...B_1^-1(P))``, ``B^-1(v) = R^-1 (v - t)``.
  For XFYZ: ``P_W = R_X^-1 (R_Y (R_Z T + Z) + Y - X)``, the bracket of Eq. 2.

Every component error is an approximation function of its own axis position:
Legendre polynomials P1..Pn of the position normalised to [-1, 1] over the
measured range (the recordings' ``truth.json`` convention).  Constant terms
are never modelled (they are indistinguishable from the tracker pose).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre as npleg

from .errors import ConfigError

AXES = ("x", "y", "z")
AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
#: the rotary axes (ISO 841): A about X, B about Y, C about Z; the component of the nominal direction
ROTARY = ("a", "b", "c")
ROTARY_INDEX = {"a": 0, "b": 1, "c": 2}
#: names of the 18 component errors, in parameter order ("dy(x)": straightness of X in Y)
COMPONENT_ERRORS = tuple(f"{kind}{c}({a})" for a in AXES for kind in ("d", "e") for c in AXES)
#: the six error motions of each rotary axis ("dx(c)": radial motion of C along X; "ez(c)": its angular
#: positioning error), in the carrier's frame (the machine frame at all axes zero)
ROTARY_COMPONENT_ERRORS = tuple(f"{kind}{c}({a})" for a in ROTARY for kind in ("d", "e") for c in AXES)
SQUARENESS = ("sxy", "sxz", "syz")


def parse_error_name(name: str):
    """Split ``"dy(x)"`` into ``("d", "y", "x")`` (also a rotary axis' ``"dx(c)"``)."""
    if name not in COMPONENT_ERRORS and name not in ROTARY_COMPONENT_ERRORS:
        raise ConfigError(f"unknown component error {name!r}; expected one of {', '.join(COMPONENT_ERRORS)} "
                          "(or the same with a rotary axis a, b, c)")
    return name[0], name[1], name[3]


def is_rotary(axis: str) -> bool:
    return axis in ROTARY_INDEX


#: the terms of a rotary axis' error motion: "O" the constant (location and zero errors, ISO 230-7), "c<n>" and
#: "s<n>" the Fourier terms cos(n theta), sin(n theta) of the commanded angle (the angle-dependent component
#: errors of ISO 230-1); Param.order numbers them 0, 1, 2, 3, 4 ... (O, c1, s1, c2, s2 ...)
def rotary_term(order: int) -> str:
    return "O" if order == 0 else f"{'cs'[(order - 1) % 2]}{(order + 1) // 2}"


def rotary_location_parameters(axis: str) -> list:
    """The location and zero errors of a rotary axis (ISO 230-7), as parameter names: the two offsets of its
    average line perpendicular to it, its two orientation errors and its zero error (``dx(c)[O]`` = EXOC ...)."""
    k = ROTARY_INDEX[axis]
    out = [f"d{c}({axis})[O]" for j, c in enumerate(AXES) if j != k]
    out += [f"e{c}({axis})[O]" for j, c in enumerate(AXES) if j != k]
    return out + [f"e{AXES[k]}({axis})[O]"]


def is_straightness(name: str) -> bool:
    kind, comp, axis = parse_error_name(name)
    return kind == "d" and comp != axis


@dataclass(frozen=True)
class RotaryAxis:
    """The nominal geometry of a rotary axis: a point of its average line (mm, machine frame with every axis at
    zero) and the sense of its nominal direction (+1: +X for A, +Y for B, +Z for C; -1: the opposite).  A
    commanded angle +theta turns the carried element right-handed about ``sign * e_k`` by theta."""

    letter: str  # "a", "b" or "c"
    pivot: tuple  # (3,) mm
    sign: float = 1.0

    @property
    def index(self) -> int:
        """The component of the nominal direction (0 for A, 1 for B, 2 for C)."""
        return ROTARY_INDEX[self.letter]

    @property
    def direction(self) -> np.ndarray:
        u = np.zeros(3)
        u[self.index] = self.sign
        return u


def check_code(code: str) -> str:
    """The machine code upper-cased, or a ConfigError: X, Y, Z and F once each, and at most one of each rotary
    letter A, B, C on either side of F."""
    c = str(code).strip().upper()
    linear = "".join(ch for ch in c if ch in "FXYZ")
    rotary = [ch for ch in c if ch in "ABC"]
    if sorted(linear) != sorted("FXYZ") or len(rotary) != len(set(rotary)) or len(linear) + len(rotary) != len(c):
        raise ConfigError(
            f"machine configuration {code!r}: expected the letters X, Y, Z and F once each (for example XFYZ, FXYZ, "
            "XYFZ), and for a five-axis machine at most one of each rotary letter A, B, C on either side of F "
            "(CAFXYZ, FXYZCB, CFXYZB)"
        )
    return c


@dataclass(frozen=True)
class Configuration:
    """A kinematic configuration such as ``XFYZ`` (3 axes) or ``CAFXYZ`` (five axes: rotary letters on either side
    of ``F``, each carried by the letter before it reading away from ``F``).  ``rotary``: the geometry of each
    rotary axis (:class:`RotaryAxis`), in the order a, b, c."""

    code: str
    workpiece: tuple  # workpiece-side axes, the one on the bed first
    tool: tuple  # tool-side axes, the one on the bed first
    rotary: tuple = ()

    @classmethod
    def parse(cls, code: str, rotary=None) -> "Configuration":
        """``rotary``: {letter: RotaryAxis} (or a sequence of them) for every rotary letter of the code; required
        when the code has one (a rotary axis without its pivot and direction has no chain)."""
        c = check_code(code)
        i = c.index("F")
        workpiece = tuple(ch.lower() for ch in reversed(c[:i]))
        tool = tuple(ch.lower() for ch in c[i + 1 :])
        given = {}
        for r in (rotary.values() if isinstance(rotary, dict) else rotary or ()):
            given[r.letter] = r
        letters = sorted(ch for ch in workpiece + tool if is_rotary(ch))
        missing = [ch.upper() for ch in letters if ch not in given]
        if missing:
            raise ConfigError(f"machine configuration {c!r}: rotary axis {', '.join(missing)} has no pivot and "
                              f"direction ([rotary.{missing[0]}] pivot, direction)")
        extra = sorted(set(given) - set(letters))
        if extra:
            raise ConfigError(f"machine configuration {c!r} has no rotary axis {', '.join(x.upper() for x in extra)}, "
                              f"but [rotary.{extra[0].upper()}] describes one")
        return cls(c, workpiece, tool, tuple(given[ch] for ch in letters))

    def side(self, axis: str) -> int:
        """+1 for a tool-side axis, -1 for a workpiece-side axis."""
        return 1 if axis in self.tool else -1

    @property
    def rotary_letters(self) -> tuple:
        return tuple(r.letter for r in self.rotary)

    def rotary_axis(self, letter: str) -> RotaryAxis:
        for r in self.rotary:
            if r.letter == letter:
                return r
        raise KeyError(letter)


ALL_CONFIGURATIONS = tuple(
    "".join(p) for p in __import__("itertools").permutations("FXYZ")
)


@dataclass
class Param:
    """One identifiable or simulated parameter of the error model."""

    name: str  # e.g. "dy(x)[P2]" or "sxy"
    unit: str  # "mm" or "rad"
    error: str  # component error name or squareness name
    order: int  # Legendre order (0 for squareness and for constant terms)

    @property
    def is_squareness(self) -> bool:
        return self.error in SQUARENESS


@dataclass
class ErrorModel:
    """Parameterisation of the 21 rigid-body errors of the linear axes and the error motions of each rotary axis.

    ``degrees`` maps each component error to its Legendre degree (0 = not
    modelled).  ``ranges`` gives each axis' normalisation interval.  With
    ``straightness_convention="iso230"`` the P1 term of each straightness
    error is left out: its linear part is carried by squareness and the
    tracker rotation, which the data cannot tell apart from it (the
    reporting convention of mtbudget, see docs/model.md).  A rigid rotation
    also turns the tool offset, which linear straightness does not; to keep
    the same model space, the angular errors of ``tool_axis`` (the axis that
    carries the tool) then get a constant P0 term: a tilt of the tool holder
    that shows only through tool offsets.

    ``rotary``: {letter: harmonics} of the rotary axes.  Each has its location and zero errors (ISO 230-7: the two
    offsets of its average line and its two orientation errors perpendicular to it, and its zero error: ``dx(c)[O]``
    = EXOC, ``dy(c)[O]`` = EYOC, ``ex(c)[O]`` = EAOC, ``ey(c)[O]`` = EBOC, ``ez(c)[O]`` = ECOC), and with
    harmonics H > 0 the angle-dependent error motions (ISO 230-1 EXC ... ECC) as Fourier terms ``[c1]``, ``[s1]``
    ... ``[cH]``, ``[sH]`` of the commanded angle; the c1/s1 terms of the radial and tilt motions are left out
    (they trade with the next element's location errors, FORMAT-3 section 5).  ``angle_unit`` of those terms:
    the angle-dependent terms are in mm and rad like the others.
    """

    ranges: dict
    degrees: dict
    squareness: bool = True
    straightness_convention: str = "iso230"  # or "free"
    tool_axis: str | None = None
    rotary: dict = field(default_factory=dict)  # letter -> harmonics (int >= 0)
    params: list = field(init=False)

    def __post_init__(self):
        for name in self.degrees:
            parse_error_name(name)
            if is_rotary(name[3]):
                raise ConfigError(f"{name}: a rotary axis' error motions are set by its harmonics, not a degree")
        for a in AXES:
            lo, hi = self.ranges[a]
            used = any(int(d) > 0 for n, d in self.degrees.items() if n[3] == a)
            if used and not hi > lo:
                raise ConfigError(f"axis {a}: measured range [{lo}, {hi}] mm is empty; cannot normalise its error functions")
        if self.straightness_convention not in ("iso230", "free"):
            raise ConfigError("straightness_convention must be 'iso230' or 'free'")
        for r, h in self.rotary.items():
            if r not in ROTARY_INDEX:
                raise ConfigError(f"rotary axis {r!r}: expected a, b or c")
            if int(h) < 0:
                raise ConfigError(f"rotary axis {r.upper()}: harmonics must be >= 0, got {h}")
        self.params = []
        for name in COMPONENT_ERRORS:
            deg = int(self.degrees.get(name, 0))
            if deg < 0:
                raise ConfigError(f"{name}: degree must be >= 0, got {deg}")
            first = 2 if (self.straightness_convention == "iso230" and is_straightness(name)) else 1
            if (self.straightness_convention == "iso230" and deg and name[0] == "e" and name[3] == self.tool_axis):
                first = 0
            unit = "mm" if name[0] == "d" else "rad"
            for n in range(first, deg + 1):
                self.params.append(Param(f"{name}[P{n}]", unit, name, n))
        for r in ROTARY:
            if r not in self.rotary:
                continue
            k = ROTARY_INDEX[r]
            H = int(self.rotary[r])
            for kind in "de":
                for j, c in enumerate(AXES):
                    err = f"{kind}{c}({r})"
                    unit = "mm" if kind == "d" else "rad"
                    along = j == k  # axial motion / positioning error: no constant location term, but c1/s1
                    orders = ([] if (kind == "d" and along) else [0])
                    orders += [o for o in range(1, 2 * H + 1) if along or o > 2]
                    for o in orders:
                        self.params.append(Param(f"{err}[{rotary_term(o)}]", unit, err, o))
        if self.squareness:
            for s in SQUARENESS:
                self.params.append(Param(s, "rad", s, 0))

    @classmethod
    def default(cls, nominal: np.ndarray, max_degree: int = 3, *, angles: dict | None = None, harmonics: int = 0,
                **kw) -> "ErrorModel":
        """Degrees ``min(max_degree, distinct positions - 1)`` per axis, ranges from the data; the rotary axes of
        ``angles`` (letter -> commanded angles) with their location errors and ``harmonics`` Fourier terms."""
        nominal = np.asarray(nominal, float)
        ranges, degrees = {}, {}
        for a in AXES:
            col = nominal[:, AXIS_INDEX[a]]
            ranges[a] = (float(col.min()), float(col.max()))
            npos = len(np.unique(np.round(col, 6)))
            deg = max(0, min(max_degree, npos - 1))
            for kind in "de":
                for c in AXES:
                    degrees[f"{kind}{c}({a})"] = deg
        kw.setdefault("rotary", {r: int(harmonics) for r in sorted(angles or {})})
        return cls(ranges=ranges, degrees=degrees, **kw)

    @property
    def names(self):
        return [p.name for p in self.params]

    @property
    def units(self):
        return [p.unit for p in self.params]

    def index(self, name: str) -> int:
        return self.names.index(name)

    def normalised(self, axis: str, positions) -> np.ndarray:
        lo, hi = self.ranges[axis]
        half = 0.5 * (hi - lo) if hi > lo else 1.0
        return (np.asarray(positions, float) - 0.5 * (lo + hi)) / half

    def basis(self, nominal: np.ndarray, angles: dict | None = None) -> np.ndarray:
        """Basis value of every parameter at every point: (M, p).

        Squareness columns are 0 here (they act through the effective
        positions, see :func:`chain`).  A rotary axis' terms are 1 (location errors) and cos/sin of multiples of
        its commanded angle (``angles``: letter -> (M,) rad).
        """
        nominal = np.asarray(nominal, float)
        M = nominal.shape[0]
        B = np.zeros((M, len(self.params)))
        cache = {}
        for j, p in enumerate(self.params):
            if p.error in SQUARENESS:
                continue
            axis = p.error[3]
            if is_rotary(axis):
                if p.order == 0:
                    B[:, j] = 1.0
                    continue
                if angles is None or axis not in angles:
                    raise ConfigError(f"rotary axis {axis.upper()}: no commanded angles for its error motions")
                n = (p.order + 1) // 2
                th = np.asarray(angles[axis], float)
                col = np.cos(n * th) if p.order % 2 else np.sin(n * th)
                # a term the plan's angles do not see (sin 2c at 0, 90, 180, 270 deg) is zero, not 1e-16: the rank
                # decision equilibrates columns, and round-off would make it look identifiable
                col[np.abs(col) < 1e-12] = 0.0
                B[:, j] = col
                continue
            if axis not in cache:
                cache[axis] = self.normalised(axis, nominal[:, AXIS_INDEX[axis]])
            coef = np.zeros(p.order + 1)
            coef[p.order] = 1.0
            B[:, j] = npleg.legval(cache[axis], coef) if p.order else 1.0
        return B

    def from_coefficients(self, coefficients: dict, squareness: dict | None = None,
                          named: dict | None = None) -> np.ndarray:
        """Parameter vector from ``{"dx(x)": [P1, P2, ...]}`` (mm / rad) and squareness (rad); ``named``: other
        parameters by name (a rotary axis' ``dx(c)[O]`` ...), mm / rad.

        Terms that the model does not carry (a degree lower than given, or the
        P1 of a straightness under the iso230 convention) must be zero;
        otherwise a :class:`ConfigError` says which.
        """
        theta = np.zeros(len(self.params))
        names = self.names
        for err, coefs in coefficients.items():
            parse_error_name(err)
            for n, value in enumerate(coefs, start=1):
                key = f"{err}[P{n}]"
                if key in names:
                    theta[names.index(key)] = value
                elif value != 0.0:
                    raise ConfigError(f"{key} = {value} is not a parameter of this error model (degree or convention)")
        for s, value in (squareness or {}).items():
            if s not in SQUARENESS:
                raise ConfigError(f"unknown squareness {s!r}; expected one of {SQUARENESS}")
            if s in names:
                theta[names.index(s)] = value
            elif value != 0.0:
                raise ConfigError(f"squareness {s} is not modelled")
        for key, value in (named or {}).items():
            if key in names:
                theta[names.index(key)] = value
            elif value != 0.0:
                raise ConfigError(f"{key} = {value} is not a parameter of this error model")
        return theta

    def coefficients(self, theta: np.ndarray) -> tuple[dict, dict]:
        """Inverse of :meth:`from_coefficients` for one parameter vector (rotary terms by name in the second dict)."""
        coefs, sq = {}, {}
        for j, p in enumerate(self.params):
            if p.is_squareness:
                sq[p.error] = float(theta[j])
            elif is_rotary(p.error[3]):
                sq[p.name] = float(theta[j])
            elif p.order == 0:
                sq[f"{p.error}[P0]"] = float(theta[j])
            else:
                lst = coefs.setdefault(p.error, [0.0] * int(self.degrees[p.error]))
                lst[p.order - 1] = float(theta[j])
        return coefs, sq

    @property
    def rotary_letters(self) -> tuple:
        return tuple(r for r in ROTARY if r in self.rotary)


def skew_basis() -> np.ndarray:
    """K[c] with K[c] @ v = e_c x v (so I + sum eps_c K[c] is the paper's Eq. 6)."""
    K = np.zeros((3, 3, 3))
    K[0] = [[0, 0, 0], [0, 0, -1], [0, 1, 0]]
    K[1] = [[0, 0, 1], [0, 0, 0], [-1, 0, 0]]
    K[2] = [[0, -1, 0], [1, 0, 0], [0, 0, 0]]
    return K


_K = skew_basis()


def rotation_small(eps: np.ndarray) -> np.ndarray:
    """Eq. 6: ``I + [eps]x`` for eps (..., 3)."""
    R = skew(eps)
    R[..., 0, 0] += 1.0
    R[..., 1, 1] += 1.0
    R[..., 2, 2] += 1.0
    return R


def inverse_small(eps: np.ndarray) -> np.ndarray:
    """Closed-form inverse of Eq. 6: ``(I - [eps]x + eps eps^T) / (1 + |eps|^2)``."""
    Rinv = eps[..., :, None] * eps[..., None, :] - skew(eps)
    Rinv[..., 0, 0] += 1.0
    Rinv[..., 1, 1] += 1.0
    Rinv[..., 2, 2] += 1.0
    return Rinv / (1.0 + (eps * eps).sum(-1))[..., None, None]


def rotation_second(eps: np.ndarray) -> np.ndarray:
    """A rotary axis' error rotation to second order, ``I + [eps]x + [eps]x^2 / 2`` (eps (..., 3)): lengths kept to
    O(|eps|^4), where Eq. 6's ``I + [eps]x`` stretches them by |eps|^2 / 2 (a rotary axis' zero and orientation
    errors reach hundreds of urad, and a weakly identifiable combination of them needs the curvature right)."""
    S = skew(eps)
    R = S + 0.5 * (S @ S)
    R[..., 0, 0] += 1.0
    R[..., 1, 1] += 1.0
    R[..., 2, 2] += 1.0
    return R


def _second_order_derivative(eps: np.ndarray, v: np.ndarray, sgn: float) -> np.ndarray:
    """d/deps of ``rotation_second(sgn * eps) @ v``: ``-sgn [v]x + (eps v^T + (eps . v) I - 2 v eps^T) / 2``
    (..., 3, 3)."""
    D = -sgn * skew(v) + 0.5 * (eps[..., :, None] * v[..., None, :] - 2.0 * v[..., :, None] * eps[..., None, :])
    dot = (eps * v).sum(-1)
    for c in range(3):
        D[..., c, c] += 0.5 * dot
    return D


def rotation_exact(eps: np.ndarray) -> np.ndarray:
    """Exact rotation ``expm([eps]x)`` (Rodrigues) for eps (..., 3)."""
    th = np.linalg.norm(eps, axis=-1)[..., None, None]
    S = np.einsum("...c,cij->...ij", eps, _K)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(th > 1e-12, np.sin(th) / np.where(th > 0, th, 1), 1.0 - th**2 / 6)
        b = np.where(th > 1e-12, (1 - np.cos(th)) / np.where(th > 0, th, 1) ** 2, 0.5 - th**2 / 24)
    return np.eye(3) + a * S + b * (S @ S)


def workpiece_rotation(config: Configuration, angles: dict) -> np.ndarray | None:
    """The nominal orientation of the workpiece (table) frame in the machine frame at each pose: (M, 3, 3) R with
    ``v_machine = R v_workpiece`` for a vector (a deviation), from the workpiece-side rotary axes' commanded angles
    (``angles``: letter -> (M,) rad; the rotary axes nominal, no error motion).  With the workpiece-side axes
    ``B_1`` (on the bed) ... ``B_m`` (carrying the workpiece), ``P_W = B_m^-1(...B_1^-1(P))`` turns a machine-frame
    vector by ``R_m^T ... R_1^T``, so ``R = R_1 R_2 ... R_m`` (CAFXYZ: ``R_A(a) R_C(c)``).  None when no rotary axis
    carries the workpiece (a three-axis machine, a head-head FXYZCB): the two frames are then the same."""
    letters = [a for a in config.workpiece if is_rotary(a)]
    if not letters:
        return None
    M = len(np.atleast_1d(angles[letters[0]]))
    R = np.broadcast_to(np.eye(3), (M, 3, 3)).copy()
    for a in letters:  # the bed's first
        th = np.asarray(angles[a], float).reshape(M)
        R = R @ rotation_exact(th[:, None] * config.rotary_axis(a).direction)
    return R


@dataclass
class ChainInputs:
    """Per-point inputs of the chain, internal units.

    nominal: (M, 3) commanded axis positions; tool: (M, 3) tool offset T;
    offset / scale: dict axis -> array broadcastable to (N, M) added to the
    position / relative scale error of the axis (Eq. 15); angles: dict rotary
    letter -> (M,) commanded angles (rad), to which ``offset`` of that letter
    (rad) adds.
    """

    nominal: np.ndarray
    tool: np.ndarray
    offset: dict = field(default_factory=dict)
    scale: dict = field(default_factory=dict)
    angles: dict = field(default_factory=dict)

    def effective(self, axis: str) -> np.ndarray:
        if is_rotary(axis):
            th = np.asarray(self.angles[axis], float)[None, :]
            off = self.offset.get(axis)
            return np.atleast_2d(th if off is None else th + np.asarray(off))
        p = self.nominal[:, AXIS_INDEX[axis]][None, :]
        off = self.offset.get(axis)
        if off is not None:
            p = p + np.asarray(off)
        sc = self.scale.get(axis)
        if sc is not None:
            f = 1.0 + np.asarray(sc)
            if f.dtype == p.dtype and broadcast_shape(p.shape, f.shape) == f.shape:
                p = np.multiply(p, f, out=f)  # p * (1 + s) into the array of 1 + s: one (N, M) array fewer
            else:
                p = p * f
        return np.atleast_2d(p)


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x for v (..., 3): the matrix with [v]x u = v x u."""
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _groups(model: ErrorModel) -> dict:
    """Parameter indices of each modelled component error (contiguous slices)."""
    groups: dict = {}
    for j, p in enumerate(model.params):
        if not p.is_squareness:
            groups.setdefault(p.error, []).append(j)
    return {k: slice(v[0], v[-1] + 1) for k, v in groups.items()}


def _basis_map(model: ErrorModel, B: np.ndarray) -> np.ndarray:
    """C (M, g, p): basis value of parameter j in sensitivity column g (groups, then squareness)."""
    M, p = B.shape
    groups = _groups(model)
    sq = [n for n in SQUARENESS if n in model.names]
    C = np.zeros((M, len(groups) + len(sq), p))
    for g, idx in enumerate(groups.values()):
        C[:, g, idx] = B[:, idx]
    for k, n in enumerate(sq):
        C[:, len(groups) + k, model.names.index(n)] = 1.0
    return C


def _axis_terms(model: ErrorModel, theta: np.ndarray, B: np.ndarray):
    """Translational and angular errors per axis: dict axis -> (delta (N,M,3), eps (N,M,3))."""
    N = theta.shape[0]
    M = B.shape[0]
    out = {a: [np.zeros((N, M, 3)), np.zeros((N, M, 3))] for a in AXES + ROTARY}
    for err, idx in _groups(model).items():
        kind, comp, axis = err[0], AXIS_INDEX[err[1]], err[3]
        vals = theta[:, idx] @ B[:, idx].T  # (N, M)
        out[axis][0 if kind == "d" else 1][:, :, comp] += vals
    return out


def _squareness_index(model: ErrorModel) -> dict:
    """{squareness name: its parameter index} of the modelled squareness errors (cached with the parameter list)."""
    cached = model.__dict__.get("_sq_cache")
    if cached is None or cached[0] is not model.params:
        names = [p.name for p in model.params]
        cached = (model.params, {s: names.index(s) for s in SQUARENESS if s in names})
        model.__dict__["_sq_cache"] = cached
    return cached[1]


def _squareness(model: ErrorModel, theta: np.ndarray):
    where = _squareness_index(model)
    return {s: (theta[:, where[s], None] if s in where else 0.0) for s in SQUARENESS}


def chain(
    config: Configuration,
    model: ErrorModel,
    theta: np.ndarray,
    inputs: ChainInputs,
    *,
    exact: bool = False,
    jacobian: bool = False,
    B: np.ndarray | None = None,
    project: np.ndarray | None = None,
    row_groups: list | None = None,
):
    """Tool point in the workpiece frame for N parameter vectors.

    theta: (N, p) or (p,).  Returns P_W (N, M, 3), and with ``jacobian=True``
    also dP_W/dtheta (N, M, 3, p), exact for the Eq. 6 small-angle chain
    (``exact=False``).  With ``project`` (p, r) the Jacobian is returned
    already multiplied by it, (N, M, 3, r), without forming the full one.
    row_groups: slices of the trials; the one product of the Jacobian that
    mixes trials (BLAS rounds a row differently with the number of rows) is
    then done slice by slice, so each slice gets the bits it would get alone.

    The small-angle chain is evaluated component by component on (N, M)
    arrays (``R v = v + eps x v``, the closed-form inverse of Eq. 6 applied
    as ``(u - eps x u + eps (eps . u)) / (1 + |eps|^2)``), never through
    3 x 3 matrices per point: the same numbers as :func:`chain_reference`
    to round-off, several times faster.
    """
    if exact:
        return chain_reference(config, model, theta, inputs, exact=True, jacobian=jacobian, B=B, project=project)
    theta = np.atleast_2d(np.asarray(theta, float))
    N, M = theta.shape[0], inputs.nominal.shape[0]
    if B is None:
        B = model.basis(inputs.nominal, inputs.angles)
    if not jacobian:
        return chain_points(config, model, theta, inputs, B)
    if config.rotary:  # the formed Jacobian of a five-axis chain: the matrix form (3 x 3 per point and axis)
        return chain_reference(config, model, theta, inputs, jacobian=True, B=B, project=project)
    out, terms, t, peff, v_in, w_out = _evaluate(config, model, theta, inputs, B)
    return out, _jacobian(config, model, terms, t, peff, v_in, w_out, B, project, N, M, row_groups)


def chain_points(config: Configuration, model: ErrorModel, theta: np.ndarray, inputs: ChainInputs,
                 B: np.ndarray) -> np.ndarray:
    """The small-angle chain's points (N, M, 3), compiled (:func:`mtbudget.kernels.chain_points`): one pass per
    trial and point instead of :func:`_evaluate`'s passes over (N, M) arrays; the same arithmetic (the
    Legendre sums in order instead of through BLAS: round-off).  A trial's points depend on its own inputs
    only."""
    from .kernels import chain_points as kernel

    args = _kernel_inputs(config, model, theta, inputs, B)
    N, M = theta.shape[0], inputs.nominal.shape[0]
    scratch = np.empty((1, args[8].shape[0], 3, M))  # nothing kept for the adjoint
    return kernel(*args, np.empty((N, M, 3)), scratch, scratch, scratch)


def _slots(config: Configuration) -> dict:
    """The compiled chain's axis numbering: X, Y, Z are 0, 1, 2; the rotary axes follow in the order a, b, c."""
    return _slots_of(config.rotary_letters)


def _slots_of(letters: tuple) -> dict:
    return dict(AXIS_INDEX, **{r: 3 + i for i, r in enumerate(letters)})


def _kernel_inputs(config, model, theta, inputs, B):
    """The compiled chain's inputs: (tool axes, workpiece axes, sides, px, py, pz, tool, coef, L, sq, rdir, pivot,
    rcos, rsin)."""
    k = kernel_chain(config, model, inputs, B, theta.shape[0])
    coef, sq = kernel_parameters(k, theta)
    return (k["tool_axes"], k["wp_axes"], k["side"], k["px"], k["py"], k["pz"], k["tool"],
            coef, k["L"], sq, k["rdir"], k["pivot"], k["rcos"], k["rsin"])


def kernel_parameters(k: dict, theta: np.ndarray) -> tuple:
    """The compiled chain's per-trial inputs of the parameters theta (N, p), through the layout ``k`` of
    :func:`kernel_chain`: the coefficient table (N, A, 6, K) (``src`` -> ``dst``, zeros elsewhere) and the
    squareness errors (N, 3) (``sqi``: sxy, sxz, syz; zero where not modelled)."""
    N = theta.shape[0]
    A, K = k["L"].shape[:2]
    coef = np.zeros((N, A * 6 * K))
    coef[:, k["dst"]] = theta[:, k["src"]]
    sq = np.zeros((N, 3))
    for c, j in enumerate(k["sqi"]):  # columns sxy, sxz, syz
        if j >= 0:
            sq[:, c] = theta[:, j]
    return coef.reshape(N, A, 6, K), sq


def kernel_points(k: dict, theta: np.ndarray) -> np.ndarray:
    """The compiled chain's points (N, M, 3) of the parameters theta (N, p) through the inputs ``k`` of
    :func:`kernel_chain` (no point offsets: :meth:`mtbudget.model.MeasurementModel.machine_points` adds those):
    :func:`chain_points`' numbers from inputs built once."""
    from .kernels import chain_points as kernel

    coef, sq = kernel_parameters(k, theta)
    N, M = theta.shape[0], k["tool"].shape[0]
    scratch = np.empty((1, coef.shape[1], 3, M))  # nothing kept for the adjoint
    return kernel(k["tool_axes"], k["wp_axes"], k["side"], k["px"], k["py"], k["pz"], k["tool"], coef, k["L"], sq,
                  k["rdir"], k["pivot"], k["rcos"], k["rsin"], np.empty((N, M, 3)), scratch, scratch, scratch)


def kernel_rows(k: dict, rows: np.ndarray) -> dict:
    """The inputs ``k`` of :func:`kernel_chain` at the points ``rows`` only (every per-point array's columns, copied
    C-contiguous): the chain's points from them are the points of ``k`` at those rows, bit for bit (a point's chain
    uses that point's inputs only; nothing is summed across points)."""
    rows = np.asarray(rows, np.int64)
    out = dict(k)
    for key in ("px", "py", "pz"):
        out[key] = np.ascontiguousarray(k[key][:, rows])
    out["tool"] = np.ascontiguousarray(k["tool"][rows])
    out["L"] = np.ascontiguousarray(k["L"][:, :, rows])
    out["rcos"] = np.ascontiguousarray(k["rcos"][:, :, rows])
    out["rsin"] = np.ascontiguousarray(k["rsin"][:, :, rows])
    return out


def kernel_chain(config, model, inputs, B, N: int) -> dict:
    """What the compiled chain takes besides the parameters, for N trials: the axes (``tool_axes``, ``wp_axes``,
    ``side``), the effective positions ``px``, ``py``, ``pz`` (1 or N, M), ``tool`` (M, 3), the basis values ``L``
    (A, K, M) and where each parameter goes in the coefficient table (``src`` -> ``dst``), the squareness
    parameters' indices ``sqi`` (sxy, sxz, syz; -1 where not modelled) and the rotary axes' ``rdir``, ``pivot``,
    ``rcos``, ``rsin``: all C-contiguous, writable float64 or int64 (one compiled signature whatever the caller's
    arrays: a read-only view would be another type to numba, and another compilation)."""
    M = inputs.nominal.shape[0]
    tool_axes, wp_axes, side = _kernel_axes(config)
    L, src, dst, _ = _kernel_layout(config, model, B)
    sqi = _squareness_columns(model)
    pos = []
    for a in AXES:
        p = np.asarray(inputs.effective(a), float)
        if p.shape[0] not in (1, N) or p.shape[1] != M:
            p = np.broadcast_to(p, (N, M))
        pos.append(kernel_array(p))
    tool = np.asarray(inputs.tool, float)
    tool = kernel_array(tool if tool.shape == (M, 3) else np.broadcast_to(tool, (M, 3)))  # read, never written
    rdir, pivot, rcos, rsin = _rotary_inputs(config, inputs, N, M)
    return {"tool_axes": tool_axes, "wp_axes": wp_axes, "side": side, "px": pos[0], "py": pos[1], "pz": pos[2],
            "tool": tool, "L": L, "src": src, "dst": dst, "sqi": sqi, "rdir": rdir,
            "pivot": pivot, "rcos": rcos, "rsin": rsin}


def broadcast_shape(*shapes) -> tuple:
    """``np.broadcast_shapes(*shapes)``, without its cost when the shapes are all the same (the common case of a
    block's arrays)."""
    first = shapes[0]
    for s in shapes[1:]:
        if s != first:
            return np.broadcast_shapes(*shapes)
    return tuple(first)


def kernel_array(x) -> np.ndarray:
    """``np.require(x, np.float64, ["C", "W"])``: what a compiled kernel takes (one signature whatever the caller's
    arrays), without the call when ``x`` is such an array already."""
    if type(x) is np.ndarray and x.dtype == _F64:
        if not x.flags.c_contiguous:
            return np.ascontiguousarray(x)  # a new array (np.require's copy, without its Python)
        if x.flags.writeable:
            return x
    return np.require(x, np.float64, ["C", "W"])


_F64 = np.dtype(np.float64)


def _rotary_inputs(config, inputs, N, M):
    """Each rotary axis' direction component (R,), pivot (R, 3), and the cosine and sine (R, 1 or N, M) of the angle
    it turns by: its effective angle times the sense of its direction."""
    R = len(config.rotary)
    if not R:  # nothing that changes: remembered per number of points
        hit = _NO_ROTARY.get(M)
        if hit is None:
            hit = _NO_ROTARY[M] = (np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 1, M)), np.empty((0, 1, M)))
        return hit
    rdir = np.array([r.index for r in config.rotary], np.int64)
    pivot = np.array([r.pivot for r in config.rotary], float).reshape(R, 3)
    th = [np.asarray(inputs.effective(r.letter), float) for r in config.rotary]
    n = max(t.shape[0] for t in th)
    # each axis' cosine and sine written into its row of the (R, n, M) arrays (a trial's angles broadcast over the
    # trials where they are shared), the sine times the sense in place: the numbers of np.cos and sign * np.sin of
    # the stacked angles, without the stacked copy and the product's array (issue 31: 37.5 -> 32 us a five-axis trial)
    rcos, rsin = np.empty((R, n, M)), np.empty((R, n, M))
    for i, (r, t) in enumerate(zip(config.rotary, th)):
        np.cos(t, out=rcos[i])
        np.sin(t, out=rsin[i])
        np.multiply(float(r.sign), rsin[i], out=rsin[i])
    return rdir, pivot, rcos, rsin


_NO_ROTARY: dict = {}  # number of points -> _rotary_inputs of a machine without rotary axes (empty arrays)


def _kernel_axes(config: Configuration):
    """(tool-side axes innermost first, workpiece-side axes in order, side of each axis) as arrays; remembered on the
    (frozen) configuration."""
    hit = config.__dict__.get("_kernel_axes")
    if hit is None:
        slot = _slots(config)
        hit = (np.array([slot[a] for a in reversed(config.tool)], np.int64),
               np.array([slot[a] for a in config.workpiece], np.int64),
               np.array([float(config.side(a)) for a in AXES + config.rotary_letters]))
        object.__setattr__(config, "_kernel_axes", hit)
    return hit


def _squareness_columns(model: ErrorModel) -> np.ndarray:
    """The squareness parameters' indices (sxy, sxz, syz; -1 where not modelled) as int64, cached with the parameter
    list."""
    cached = model.__dict__.get("_sq_columns")
    if cached is None or cached[0] is not model.params:
        where = _squareness_index(model)
        cached = (model.params, np.array([where.get(s, -1) for s in SQUARENESS], np.int64))
        model.__dict__["_sq_columns"] = cached
    return cached[1]


def _kernel_layout(config: Configuration, model: ErrorModel, B: np.ndarray):
    """The compiled chain's coefficient table: basis values L (A, K, M) of each axis' orders (zero-padded
    to the largest K), and where each parameter goes in the (axis, component error, order) table: (L, src,
    dst, K); cached per model and basis, as :func:`_axis_layout`."""
    letters = config.rotary_letters
    return _per_basis(model, "_kernel_layout_cache", B, lambda: _build_kernel_layout(model, B, letters),
                      extra=letters)


def _build_kernel_layout(model: ErrorModel, B: np.ndarray, letters: tuple = ()):
    layout = _axis_layout(model, B)
    slot = _slots_of(letters)
    missing = [a for a in layout if a not in slot]
    if missing:
        raise ConfigError(f"the error model has errors of axis {missing[0].upper()}, which the machine does not have")
    K = max([1] + [lay[1].shape[0] for lay in layout.values()])
    M = B.shape[0]
    L = np.zeros((3 + len(letters), K, M))
    src, dst = [], []
    for axis, (kc, La, s, d) in layout.items():
        a = slot[axis]
        Ka = La.shape[0]
        L[a, :Ka] = La
        for j, slot_ in zip(s, d):  # slot_ = g * Ka + order index, g the component error's place in kc
            kind, comp = kc[slot_ // Ka]
            src.append(int(j))
            dst.append((a * 6 + 3 * kind + comp) * K + slot_ % Ka)
    return L, np.array(src, np.int64), np.array(dst, np.int64), K


def _per_basis(model: ErrorModel, name: str, B: np.ndarray, build, extra=None):
    """``build()``, cached on the model (``model.__dict__[name]``) per parameter list and basis values (a few
    bases kept: the identification's plan, the mesh, a tool)."""
    cache = model.__dict__.setdefault(name, {})
    key = (id(model.params), B.shape, B.tobytes(), extra)
    last = cache.get(None)  # the last basis asked: its bytes compared, not hashed (30 KB of the paper's plan: 6 us)
    if last is not None and last[0] == key:
        return last[1]
    hit = cache.get(key)
    if hit is None:
        if len(cache) > 8:
            cache.clear()
        hit = cache[key] = build()
    cache[None] = (key, hit)
    return hit


def chain_adjoint(config: Configuration, model: ErrorModel, theta: np.ndarray, inputs: ChainInputs, *,
                  B: np.ndarray | None = None, reference: bool = False):
    """The chain's points (N, M, 3) and its Jacobian as an operator: ``(P_W, adjoint)``.

    ``adjoint(v, idx=None)`` is ``J^T v``, (n, p): for machine-frame vectors v (n, M, 3) at the points,
    summed over the points, for the trials ``idx`` (positions among the N; None: all).  The Jacobian is
    the one :func:`chain` returns, at these parameters, never formed: J^T v is propagated back through
    the chain (one 3-vector per axis, ``G_a^T v``, from the transposed rotations), component by
    component on (n, M) arrays, then contracted with the basis values.  Per trial, ~30x fewer
    operations than forming J; every operation is elementwise or a reduction within one trial, so a
    trial's numbers do not depend on the other trials evaluated with it.  Compiled
    (:mod:`mtbudget.kernels`); ``reference=True``: the numpy formulation on (n, M) arrays it is tested
    against.
    """
    theta = np.atleast_2d(np.asarray(theta, float))
    if B is None:
        B = model.basis(inputs.nominal, inputs.angles)
    if reference:
        if config.rotary:  # the matrix form's Jacobian, formed: the reference of the compiled operator
            out, J = chain_reference(config, model, theta, inputs, jacobian=True, B=B)
            return out, _AdjointFormed(J)
        out, terms, _, peff, v_in, w_out = _evaluate(config, model, theta, inputs, B)
        return out, _Adjoint(config, model, terms, peff, v_in, w_out, B, theta.shape[0])
    from .kernels import chain_points

    args = _kernel_inputs(config, model, theta, inputs, B)
    N, M = theta.shape[0], inputs.nominal.shape[0]
    A = args[8].shape[0]
    kept = (np.empty((N, A, 3, M)), np.empty((N, A, 3, M)), np.empty((N, A, 3, M)))  # eps, vin, wout
    out = chain_points(*args, np.empty((N, M, 3)), *kept)
    return out, _AdjointCompiled(config, model, B, args, kept)


def vjp_layout(config: Configuration, model: ErrorModel, B: np.ndarray):
    """What the compiled J^T v (:func:`mtbudget.kernels.chain_vjp`) takes besides the forward pass: the tool-side
    axes from the bed (``tool_order``), each parameter's (axis, kind, component) (``params``, (p, 3)) and its basis
    values at the points (``basis``, (p, M)); cached per model and basis."""
    slot = _slots(config)

    def build():
        ref = _Adjoint.layout(model, B)
        params = np.array([(slot[ref["cols"][k][0]], ref["cols"][k][1], ref["cols"][k][2])
                           for k in ref["col_of"]], np.int64).reshape(-1, 3)
        return params, np.require(ref["basis"], np.float64, ["C", "W"])

    params, basis = _per_basis(model, "_vjp_layout_cache", B, build, extra=config.rotary_letters)
    return np.array([slot[a] for a in config.tool], np.int64), params, basis


class _AdjointCompiled:
    """J^T v of the small-angle chain at fixed parameters, compiled (:func:`mtbudget.kernels.chain_vjp`), from
    what the forward pass kept; the numbers of :class:`_Adjoint` to round-off."""

    def __init__(self, config, model, B, args, kept):
        self.args, self.kept = args, kept
        self.N = args[7].shape[0]
        self.tool_order, self.params, self.basis = vjp_layout(config, model, B)

    def __call__(self, v: np.ndarray, idx=None) -> np.ndarray:
        from .kernels import chain_vjp

        _, wp_axes, side, px, py, pz = self.args[:6]
        if idx is None:
            rows = np.arange(self.N, dtype=np.int64)
        else:  # the kernel does not check bounds: positions among the N trials, one per row of v
            rows = np.asarray(idx)
            if rows.ndim != 1 or rows.dtype.kind not in "iu" or (rows.size and not (
                    0 <= rows.min() and rows.max() < self.N)):
                raise IndexError(f"adjoint: idx must be positions among the {self.N} trials, got {idx!r}")
            rows = rows.astype(np.int64, copy=False)
        M = self.kept[0].shape[-1]
        if np.shape(v) != (len(rows), M, 3):
            raise ValueError(f"adjoint: v must have shape ({len(rows)}, {M}, 3), got {np.shape(v)}")
        out = np.empty((len(rows), len(self.params)))
        rdir, _, rcos, rsin = self.args[10:14]
        return chain_vjp(self.tool_order, wp_axes, side, px, py, pz, rdir, rcos, rsin, *self.kept, rows,
                         np.require(v, np.float64, ["C", "W"]), self.params, self.basis, out)


class _AdjointFormed:
    """J^T v from a formed Jacobian J (N, M, 3, p): the reference of the compiled operator for a machine with
    rotary axes (from :func:`chain_reference`)."""

    def __init__(self, J):
        self.J = J

    def __call__(self, v: np.ndarray, idx=None) -> np.ndarray:
        J = self.J if idx is None else self.J[np.asarray(idx)]
        return np.einsum("nmcp,nmc->np", J, v)


class _Adjoint:
    """J^T v of the small-angle chain at fixed parameters (see :func:`chain_adjoint`)."""

    def __init__(self, config, model, terms, peff, v_in, w_out, B, N):
        self.config, self.N = config, N
        self.eps = {a: terms[a][1] for a in AXES}
        # 1 / (1 + |eps|^2) of each workpiece axis' closed-form inverse
        self.den = {a: 1.0 / (1.0 + (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]))
                    for a, e in self.eps.items() if e is not None and a in config.workpiece}
        self.peff, self.v_in, self.w_out = peff, v_in, w_out
        lay = self.layout(model, B)
        cols, self.col_of, self.basis = lay["cols"], lay["col_of"], lay["basis"]
        self.cols = cols
        self.by_axis: dict = {}
        for k, (axis, kind, comp) in enumerate(cols):
            self.by_axis.setdefault(axis, []).append((k, kind, comp))
        self.neg_peff = {a: -np.asarray(peff[a]) for a in AXES}
        # the parameters of each column: one contiguous run (a component error's orders, or one squareness)
        self.params_of = {}
        for k in range(len(cols)):
            js = np.flatnonzero(self.col_of == k)
            if js.size:
                if js[-1] - js[0] + 1 != js.size:  # pragma: no cover - _groups gives contiguous parameter runs
                    raise ValueError("the parameters of a component error are not contiguous")
                self.params_of[k] = (int(js[0]), int(js[-1]) + 1)
            else:
                self.params_of[k] = (0, 0)

    @staticmethod
    def layout(model, B) -> dict:
        """The sensitivity columns (axis, kind 0 translation / 1 rotation / 2 squareness, component), the
        column of each parameter (p,) and each parameter's basis values (p, M)."""
        names = model_names(model)
        # column g of the sensitivities -> the parameters it carries, with their basis values (M, p)
        cols = [(axis, kind, comp) for axis, kind, comp, _ in _component_groups(model)]
        cols += [(axis, 2, c) for name, axis, c in _SQ_COLUMNS if name in names]
        C = _basis_map(model, B)  # (M, g, p): one non-zero column per parameter
        col_of = np.argmax(np.abs(C).max(axis=0) != 0, axis=0)  # (p,) the column of each parameter
        basis = np.ascontiguousarray(C[:, col_of, np.arange(C.shape[2])].T)  # (p, M)
        return {"cols": cols, "col_of": col_of, "basis": basis}

    def _rows(self, x, idx):
        if idx is None or np.ndim(x) < 2 or np.shape(x)[0] != self.N or self.N == 1:
            return x
        return x[idx]

    def __call__(self, v: np.ndarray, idx=None) -> np.ndarray:
        cfg = self.config
        sub = (lambda x: x) if idx is None else (lambda x: self._rows(x, idx))
        u = [v[..., 0], v[..., 1], v[..., 2]]
        g = {}
        for a in reversed(cfg.workpiece):  # G_a^T v = Rinv_a^T ... Rinv_wm^T v
            e = self.eps[a]
            if e is not None:
                e = [sub(x) for x in e]
                c = _cross(e, u)
                dot = e[0] * u[0] + e[1] * u[1] + e[2] * u[2]
                den = sub(self.den[a])
                u = [(u[k] + c[k] + e[k] * dot) * den for k in range(3)]
            g[a] = u
        for j, a in enumerate(cfg.tool):  # G_a^T v = R_a-1^T ... R_1^T MW^T v
            g[a] = u
            e = self.eps[a]
            if e is not None and j < len(cfg.tool) - 1:
                c = _cross([sub(x) for x in e], u)
                u = [u[k] - c[k] for k in range(3)]
        n = u[0].shape[0]
        out = np.empty((n, self.basis.shape[0]))
        for axis, cols in self.by_axis.items():
            ga = g[axis]
            tool = axis in cfg.tool
            cross = None
            for k, kind, comp in cols:
                if kind == 0:  # dP/dt_axis = +G (tool side) or -G (workpiece side)
                    h = ga[comp] if tool else -ga[comp]
                elif kind == 1:
                    if cross is None:
                        if tool:  # d/deps of (v + eps x v) is -G [v_in]x; transposed: v_in x g
                            cross = _cross([sub(x) for x in self.v_in[axis]], ga)
                        else:  # + G [w_out]x; transposed: g x w_out
                            cross = _cross(ga, [sub(x) for x in self.w_out[axis]])
                    h = cross[comp]
                else:  # squareness: the column of dP/dt_axis times -side * position, dP/dt_axis = side * G
                    h = ga[comp] * sub(self.neg_peff[axis])
                # sum over the points of h times each of the column's parameters' basis values: one dot product
                # over the points per trial and parameter (einsum's inner loop: the same for any number of trials)
                lo, hi = self.params_of[k]
                out[:, lo:hi] = np.einsum("nm,jm->nj", h, self.basis[lo:hi])
        return out


#: squareness columns of the sensitivities: (name, the axis whose translation carries it, component)
_SQ_COLUMNS = (("sxy", "y", 0), ("sxz", "z", 0), ("syz", "z", 1))


def _evaluate(config, model, theta, inputs, B):
    """The small-angle chain, component by component: (P_W, terms, t, peff, v_in, w_out)."""
    N, M = theta.shape[0], inputs.nominal.shape[0]
    terms = _axis_components(model, theta, B)
    sq = _squareness(model, theta)
    t, peff = {}, {}
    for a in AXES:
        p = inputs.effective(a)  # (1, M) or (N, M)
        peff[a] = p
        s = float(config.side(a))
        d = [None, None, None]
        d[AXIS_INDEX[a]] = p if s > 0 else -p
        if a == "y" and "sxy" in model_names(model):
            d[0] = (p * sq["sxy"]) * -s
        elif a == "z":
            if "sxz" in model_names(model):
                d[0] = (p * sq["sxz"]) * -s
            if "syz" in model_names(model):
                d[1] = (p * sq["syz"]) * -s
        delta = terms[a][0]
        t[a] = [d[c] if delta[c] is None else (delta[c] if d[c] is None else d[c] + delta[c]) for c in range(3)]
    # tool side: P = A_1(A_2(...A_n(T))), A(v) = v + eps x v + t
    tool = np.asarray(inputs.tool, float)
    v = [tool[:, 0], tool[:, 1], tool[:, 2]]
    v_in = {}
    for a in reversed(config.tool):
        v_in[a] = v
        e = terms[a][1]
        if e is not None:
            v = _add(v, _cross(e, v))
        v = _add(v, t[a])
    # workpiece side: P_W = B_m^-1(...B_1^-1(P)), B^-1(w) = R^-1 (w - t)
    w = v
    w_out = {}
    for a in config.workpiece:
        u = _sub(w, t[a])
        e = terms[a][1]
        if e is None:
            w = u
        else:
            c = _cross(e, u)
            dot = e[0] * u[0] + e[1] * u[1] + e[2] * u[2]
            den = 1.0 + (e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
            w = [(u[k] - c[k] + e[k] * dot) / den for k in range(3)]
        w_out[a] = w
    out = np.empty((N, M, 3))
    for k in range(3):
        out[:, :, k] = w[k]
    return out, terms, t, peff, v_in, w_out


def model_names(model: ErrorModel) -> frozenset:
    """The parameter names of ``model`` as a set (cached on the model with its parameter list)."""
    cached = model.__dict__.get("_names_cache")
    if cached is None or cached[0] is not model.params:
        cached = (model.params, frozenset(p.name for p in model.params))
        model.__dict__["_names_cache"] = cached
    return cached[1]


def _cross(e, v):
    """e x v for 3-lists of arrays (e entries may be None: zero)."""
    e0, e1, e2 = (0.0 if x is None else x for x in e)
    return [e1 * v[2] - e2 * v[1], e2 * v[0] - e0 * v[2], e0 * v[1] - e1 * v[0]]


def _add(a, b):
    return [x if y is None else y if x is None else x + y for x, y in zip(a, b)]


def _sub(a, b):
    return [x if y is None else -y if x is None else x - y for x, y in zip(a, b)]


def _component_groups(model: ErrorModel):
    """[(axis, 0 for d / 1 for e, component, parameter slice)] of the modelled component errors (cached)."""
    cached = model.__dict__.get("_component_cache")
    if cached is None or cached[0] is not model.params:
        groups = [(err[3], 0 if err[0] == "d" else 1, AXIS_INDEX[err[1]], idx) for err, idx in _groups(model).items()]
        cached = (model.params, groups)
        model.__dict__["_component_cache"] = cached
    return cached[1]


def _axis_layout(model: ErrorModel, B: np.ndarray):
    """Per axis: the Legendre values of every order used (M, K) and where each parameter goes in the
    (component error, order) coefficient table of that axis; cached per model and basis."""
    return _per_basis(model, "_axis_layout_cache", B, lambda: _build_axis_layout(model, B))


def _build_axis_layout(model: ErrorModel, B: np.ndarray):
    layout = {}
    for axis in AXES + model.rotary_letters:
        groups = [(kind, comp, idx) for ax, kind, comp, idx in _component_groups(model) if ax == axis]
        if not groups:
            continue
        orders = sorted({model.params[j].order for *_, idx in groups for j in range(idx.start, idx.stop)})
        cols = {}  # order -> a column of B holding its values at the points (the same for every component)
        for *_, idx in groups:
            for j in range(idx.start, idx.stop):
                cols.setdefault(model.params[j].order, j)
        L = np.ascontiguousarray(np.stack([B[:, cols[o]] for o in orders]))  # (K, M)
        K = len(orders)
        src, dst = [], []
        for g, (kind, comp, idx) in enumerate(groups):
            for j in range(idx.start, idx.stop):
                src.append(j)
                dst.append(g * K + orders.index(model.params[j].order))
        layout[axis] = ([(kind, comp) for kind, comp, _ in groups], L, np.array(src), np.array(dst))
    return layout


def _axis_components(model: ErrorModel, theta: np.ndarray, B: np.ndarray) -> dict:
    """axis -> (delta, eps): 3-lists of (N, M) arrays (None where the model has no such error; eps None if none).

    Per axis one BLAS product, (N x component errors, orders <= 4) x (orders, M): every component error of an
    axis is a combination of the same Legendre polynomials of that axis' position.  A trial's values must not
    depend on the other trials evaluated with it (the engine identifies several blocks together and promises
    the numbers of each block alone): OpenBLAS gives every row the same bits for any number of rows >= 2 at
    an inner dimension <= 4, but a single row goes through gemv, which rounds differently; a single trial is
    therefore evaluated as two (``tests/test_scaleout.py`` checks the invariance).  Beyond 4 orders the terms
    are summed elementwise, in order.
    """
    out = {a: ([None, None, None], [None, None, None]) for a in AXES}
    N = theta.shape[0]
    single = N == 1
    th = np.concatenate([theta, theta]) if single else theta
    n = th.shape[0]
    for axis, (kc, L, src, dst) in _axis_layout(model, B).items():
        K = L.shape[0]
        coef = np.zeros((n, len(kc) * K))
        coef[:, dst] = th[:, src]
        coef = coef.reshape(n * len(kc), K)
        if K <= 4:
            vals = coef @ L
        else:
            vals = coef[:, :1] * L[0]
            for k in range(1, K):
                vals = vals + coef[:, k:k + 1] * L[k]
        vals = vals.reshape(n, len(kc), L.shape[1])
        for g, (kind, comp) in enumerate(kc):
            out[axis][kind][comp] = vals[:1, g] if single else vals[:, g]
    return {a: (d, None if all(x is None for x in e) else [0.0 if x is None else x for x in e])
            for a, (d, e) in out.items()}


def _full(x, N, M):
    return np.broadcast_to(np.zeros(()) if x is None else x, (N, M))


def _mm33(A, Bm):
    """A @ Bm for stacks of 3 x 3 matrices (..., 3, 3), by broadcasting (no per-matrix BLAS call)."""
    return A[..., :, 0, None] * Bm[..., None, 0, :] + A[..., :, 1, None] * Bm[..., None, 1, :] \
        + A[..., :, 2, None] * Bm[..., None, 2, :]


def _stack3(v, N, M):
    out = np.empty((N, M, 3))
    for k in range(3):
        out[:, :, k] = 0.0 if v[k] is None else v[k]
    return out


def _skew_stack(v, N, M):
    """[v]x (N, M, 3, 3) from a 3-list of arrays."""
    S = np.zeros((N, M, 3, 3))
    v0, v1, v2 = (_full(x, N, M) for x in v)
    S[..., 0, 1], S[..., 0, 2] = -v2, v1
    S[..., 1, 0], S[..., 1, 2] = v2, -v0
    S[..., 2, 0], S[..., 2, 1] = -v1, v0
    return S


def _rows_cross(G, v, sign):
    """sign * G [v]x for (N, M, 3, 3) G and a 3-list v of arrays: row i of G [v]x is (row i of G) x v."""
    v0, v1, v2 = (x[..., None] for x in v)
    out = np.empty(np.broadcast_shapes(G.shape, np.shape(v0)[:-1] + (3, 3)))
    out[..., 0] = G[..., 1] * v2 - G[..., 2] * v1
    out[..., 1] = G[..., 2] * v0 - G[..., 0] * v2
    out[..., 2] = G[..., 0] * v1 - G[..., 1] * v0
    if sign < 0:
        np.negative(out, out=out)
    return out


def _jacobian(config, model, terms, t, peff, v_in, w_out, B, project, N, M, row_groups=None):
    """dP_W/dtheta (N, M, 3, p or r) of the small-angle chain, from the chain's intermediate points."""
    eye = np.eye(3)
    R, Rinv = {}, {}
    for a in AXES:
        e = terms[a][1]
        R[a] = Rinv[a] = None
        if e is None:
            continue
        if a in config.tool:
            if a != config.tool[-1]:  # the last tool axis' rotation multiplies nothing the Jacobian needs
                R[a] = _skew_stack(e, N, M) + eye
        else:
            E = np.stack([_full(x, N, M) for x in e], axis=-1)
            Ri = E[..., :, None] * E[..., None, :] - _skew_stack(e, N, M)
            Ri += eye
            Rinv[a] = Ri / (1.0 + (E * E).sum(-1))[..., None, None]

    def mul(A, Bm):  # matrix product where None stands for the identity
        return Bm if A is None else A if Bm is None else _mm33(A, Bm)

    MW = None
    suffix = {}
    for a in reversed(config.workpiece):
        suffix[a] = MW
        MW = mul(MW, Rinv[a])
    dT, dE = {}, {}
    Qp = None
    ident = np.broadcast_to(eye, (N, M, 3, 3))
    for j, a in enumerate(config.tool):
        G = mul(MW, Qp)
        G = ident if G is None else G
        dT[a] = G
        dE[a] = _rows_cross(G, v_in[a], -1.0)
        if j < len(config.tool) - 1:
            Qp = mul(Qp, R[a])
    for a in config.workpiece:
        G = mul(suffix[a], Rinv[a])
        G = ident if G is None else G
        dT[a] = -G
        dE[a] = _rows_cross(G, w_out[a], 1.0)
    s = config.side
    names = model_names(model)
    groups = _component_groups(model)
    n_cols = len(groups) + sum(n in names for n in SQUARENESS)
    Hm = np.empty((M, N, 3, n_cols))  # point-major, so that one batched product over the points forms J
    k = 0
    while k < len(groups):
        axis, kind, comp, _ = groups[k]
        src = (dT if kind == 0 else dE)[axis]
        if comp == 0 and k + 2 < len(groups) and [g[:3] for g in groups[k:k + 3]] == [(axis, kind, c) for c in range(3)]:
            Hm[..., k:k + 3] = src.transpose(1, 0, 2, 3)  # the three columns of one axis' errors at once
            k += 3
        else:
            Hm[..., k] = src[..., comp].transpose(1, 0, 2)
            k += 1
    for name, axis, c in (("sxy", "y", 0), ("sxz", "z", 0), ("syz", "z", 1)):
        if name in names:
            Hm[..., k] = (dT[axis][..., c] * (-s(axis) * peff[axis])[..., None]).transpose(1, 0, 2)
            k += 1
    C = _projected_basis_map(model, B, project)
    if row_groups is None:
        return (Hm.reshape(M, 3 * N, n_cols) @ C).reshape(M, N, 3, C.shape[-1]).transpose(1, 0, 2, 3)
    J = np.empty((M, N, 3, C.shape[-1]))
    for sl in row_groups:
        h = Hm[:, sl]
        J[:, sl] = (h.reshape(M, 3 * h.shape[1], n_cols) @ C).reshape(M, h.shape[1], 3, C.shape[-1])
    return J.transpose(1, 0, 2, 3)


def _projected_basis_map(model: ErrorModel, B: np.ndarray, project: np.ndarray | None) -> np.ndarray:
    """``_basis_map(model, B) @ project`` (M, g, r), cached per model, basis and projection (it depends on no trial)."""
    cache = model.__dict__.setdefault("_basis_map_cache", {})
    key = (id(model.params), B.shape, B.tobytes(), None if project is None else (project.shape, project.tobytes()))
    C = cache.get(key)
    if C is None:
        if len(cache) > 16:
            cache.clear()
        C = _basis_map(model, B)
        if project is not None:
            C = C @ project
        C.flags.writeable = False
        cache[key] = C
    return C


def chain_reference(
    config: Configuration,
    model: ErrorModel,
    theta: np.ndarray,
    inputs: ChainInputs,
    *,
    exact: bool = False,
    jacobian: bool = False,
    B: np.ndarray | None = None,
    project: np.ndarray | None = None,
):
    """:func:`chain` written with a 3 x 3 matrix per point and axis (the reference; also the exact rotation).

    A rotary axis k maps what it carries to its carrier by ``G_k(v) = p_k + delta_k + R_k R_nom(theta_k) (v - p_k)``
    (FORMAT-3 section 4): the nominal turn about its pivot, then its error motion as a linear axis', its rotation to
    second order (``R_k = I + [eps_k]x + [eps_k]x^2 / 2``, :func:`rotation_second`; the zero error is the component
    of eps_k along the axis).
    """
    theta = np.atleast_2d(np.asarray(theta, float))
    N, M = theta.shape[0], inputs.nominal.shape[0]
    if B is None:
        B = model.basis(inputs.nominal, inputs.angles)
    terms = _axis_terms(model, theta, B)
    sq = _squareness(model, theta)
    rot = rotation_exact if exact else rotation_small
    t, R, peff, Rn, pivot = {}, {}, {}, {}, {}
    for a in AXES:
        p = np.broadcast_to(inputs.effective(a), (N, M))
        peff[a] = p
        d = np.zeros((N, M, 3))
        d[:, :, AXIS_INDEX[a]] = p
        if a == "y":
            d[:, :, 0] -= p * sq["sxy"]
        elif a == "z":
            d[:, :, 0] -= p * sq["sxz"]
            d[:, :, 1] -= p * sq["syz"]
        t[a] = config.side(a) * d + terms[a][0]
        R[a] = rot(terms[a][1])
    for r in config.rotary:
        a = r.letter
        pivot[a] = np.asarray(r.pivot, float)
        t[a] = pivot[a] + terms[a][0]
        R[a] = rotation_exact(terms[a][1]) if exact else rotation_second(terms[a][1])
        th = np.broadcast_to(inputs.effective(a), (N, M))
        Rn[a] = rotation_exact(th[..., None] * r.direction)  # (N, M, 3, 3)
    # tool side: P = A_1(A_2(...A_n(T)))
    v = np.broadcast_to(np.asarray(inputs.tool, float), (N, M, 3)).copy()
    v_in = {}
    for a in reversed(config.tool):
        if a in Rn:
            v = np.einsum("nmij,nmj->nmi", Rn[a], v - pivot[a])
        v_in[a] = v
        v = np.einsum("nmij,nmj->nmi", R[a], v) + t[a]
    P = v
    # workpiece side: P_W = B_m^-1(...B_1^-1(P))
    w = P
    Rinv, w_out, w_in = {}, {}, {}
    for a in config.workpiece:
        if exact:
            Rinv[a] = np.swapaxes(R[a], -1, -2)
        else:  # Eq. 6's closed-form inverse; a rotary axis' second-order rotation by -eps
            Rinv[a] = rotation_second(-terms[a][1]) if a in Rn else inverse_small(terms[a][1])
        w_in[a] = w - t[a]
        w = np.einsum("nmij,nmj->nmi", Rinv[a], w_in[a])
        w_out[a] = w
        if a in Rn:
            w = np.einsum("nmji,nmj->nmi", Rn[a], w) + pivot[a]
    if not jacobian:
        return w
    if exact:
        raise ValueError("the analytic Jacobian is defined for the Eq. 6 small-angle chain only")

    def mul(A, Bm):  # matrix product where None stands for the identity
        return Bm if A is None else A if Bm is None else A @ Bm

    # the linear part of each workpiece-side map (a rotary axis: its turn back after its error motion's inverse)
    Li = {a: (np.swapaxes(Rn[a], -1, -2) @ Rinv[a] if a in Rn else Rinv[a]) for a in config.workpiece}
    # M_W = R_bm^-1 ... R_b1^-1 (dP_W/dP); suffix products for workpiece axes
    MW = None
    suffix = {}
    for a in reversed(config.workpiece):
        suffix[a] = MW  # product of the inverses after axis a
        MW = mul(MW, Li[a])
    # tool side prefix products Q_i = R_1 ... R_{i-1} (a rotary axis' linear part: R_k R_nom)
    dT, dE = {}, {}  # dP_W/dt_a (N,M,3,3), dP_W/deps_a (N,M,3,3)
    Q = None
    for a in config.tool:
        G = mul(MW, Q)
        G = np.broadcast_to(np.eye(3), (N, M, 3, 3)) if G is None else G
        dT[a] = G
        # column c is G (e_c x v) = -G [v]x e_c (a rotary axis: the derivative of its second-order rotation)
        dE[a] = G @ _second_order_derivative(terms[a][1], v_in[a], 1.0) if a in Rn else -(G @ skew(v_in[a]))
        Q = mul(Q, R[a] @ Rn[a] if a in Rn else R[a])
    for a in config.workpiece:
        G = mul(suffix[a], Li[a])
        dT[a] = -G
        dE[a] = (G @ skew(w_out[a]) if a not in Rn else
                 mul(suffix[a], np.swapaxes(Rn[a], -1, -2)) @ _second_order_derivative(terms[a][1], w_in[a], -1.0))
    # dP_W/dtheta[n,m,:,j] = sum_g H[n,m,:,g] C[m,g,j]: H holds the chain's sensitivity to each
    # component error (and squareness), C the basis values; one batched BLAS product forms it.
    H, C = [], _basis_map(model, B)
    for err in _groups(model):
        kind, comp, axis = err[0], AXIS_INDEX[err[1]], err[3]
        H.append((dT[axis] if kind == "d" else dE[axis])[..., comp])
    s = config.side
    names = model.names
    if "sxy" in names:
        H.append(dT["y"][..., 0] * (-s("y") * peff["y"])[..., None])
    if "sxz" in names:
        H.append(dT["z"][..., 0] * (-s("z") * peff["z"])[..., None])
    if "syz" in names:
        H.append(dT["z"][..., 1] * (-s("z") * peff["z"])[..., None])
    if project is not None:
        C = C @ project
    Hm = np.stack(H, axis=-1).transpose(1, 0, 2, 3).reshape(M, 3 * N, len(H))
    J = (Hm @ C).reshape(M, N, 3, C.shape[-1]).transpose(1, 0, 2, 3)
    return w, J
