"""A machine-readable Digital Calibration Certificate (PTB DCC 3.3.0, D-SI quantities) of a run or of a recording.

One certificate for either kind of statement (``statement_tree``): a run's a priori statement (``dcc_tree``) and a
recording's a posteriori one (``posterior_dcc_tree``, ``mtbudget posterior --out``), with the [report] table of the
configuration or of recording.toml.

The same statement as report.md (``report.headline``), as XML a laboratory's
software reads: the administrative data (software, core data, the item, the
laboratory, the responsible person, the customer, the statements: kind of
statement, traceability, decision rule) from the optional ``[report]`` table
of the configuration, and the results as D-SI quantities: per axis the
largest and the RMS expanded uncertainty over the mesh (``si:expandedUnc``,
k from the coverage: 2 at 95 %), and for every mesh point and axis the estimate with its Monte Carlo
coverage interval (``si:coverageInterval``: standard uncertainty, interval
ends, coverage probability), and the ``[[features]]`` of the run with their decisions.  Units are D-SI unit strings (``\\micro\\metre``,
``\\milli\\metre``).  Fields the configuration does not state are written as
"not stated", never invented.

Schema: https://ptb.de/dcc/v3.3.0/ (dcc.xsd, which imports the D-SI
SI_Format.xsd).  ``tests/test_report_dcc.py`` validates the output with
``xmlschema`` when those files are in ``tests/data/dcc/`` and reads it back
with ``pydcc``.
"""

from __future__ import annotations

import hashlib
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from . import __version__
from .errors import ConfigError
from .report import headline, table_frame

DCC_NS = "https://ptb.de/dcc"
SI_NS = "https://ptb.de/si"
SCHEMA_VERSION = "3.3.0"
SCHEMA_LOCATION = "https://ptb.de/dcc https://ptb.de/dcc/v3.3.0/dcc.xsd"
#: mtbudget's display units -> D-SI unit strings
DSI_UNITS = {"µm": r"\micro\metre", "um": r"\micro\metre", "mm": r"\milli\metre", "urad": r"\micro\radian",
             "µrad": r"\micro\radian", "deg": r"\degree"}
NOT_STATED = "not stated"

ET.register_namespace("dcc", DCC_NS)
ET.register_namespace("si", SI_NS)


def _d(tag):
    return f"{{{DCC_NS}}}{tag}"


def _s(tag):
    return f"{{{SI_NS}}}{tag}"


def _sub(parent, tag, text=None, **attrib):
    el = ET.SubElement(parent, tag, attrib)
    if text is not None:
        el.text = str(text)
    return el


def _text(parent, tag, text: str):
    """A dcc:textType element: <tag><dcc:content lang="en">text</dcc:content></tag>."""
    el = _sub(parent, _d(tag))
    _sub(el, _d("content"), text, lang="en")
    return el


def _contact(parent, tag, name: str | None, country: str, strict: bool = True):
    el = _sub(parent, _d(tag))
    _text(el, "name", name or NOT_STATED)
    if strict:  # contactType requires a location
        loc = _sub(el, _d("location"))
        _sub(loc, _d("countryCode"), country)
    return el


def _num(x: float, nd: int) -> str:
    return f"{x:.{nd}f}"


def _real(parent, label: str, value: float, unit: str, nd: int, *, U=None, k=None, p=None, interval=None, u=None,
          distribution: str | None = "normal"):
    """An si:real: value and unit, with an expanded uncertainty (U, k, p; ``distribution`` what p assumes, None: no
    claim) or a coverage interval (u, [lo, hi], p)."""
    r = _sub(parent, _s("real"))
    _sub(r, _s("label"), label)
    _sub(r, _s("value"), _num(value, nd))
    _sub(r, _s("unit"), unit)
    if U is not None:
        e = _sub(r, _s("expandedUnc"))
        _sub(e, _s("uncertainty"), _num(U, nd))
        _sub(e, _s("coverageFactor"), f"{k:g}")
        _sub(e, _s("coverageProbability"), f"{p:g}")
        if distribution:
            _sub(e, _s("distribution"), distribution)
    elif interval is not None:
        c = _sub(r, _s("coverageInterval"))
        _sub(c, _s("standardUnc"), _num(u, nd))
        _sub(c, _s("intervalMin"), _num(interval[0], nd))
        _sub(c, _s("intervalMax"), _num(interval[1], nd))
        _sub(c, _s("coverageProbability"), f"{p:g}")
    return r


def _quantity(parent, name: str, **real):
    q = _sub(parent, _d("quantity"))
    _text(q, "name", name)
    _real(q, **real)
    return q


def certificate_id(res, fields: dict) -> str:
    """The [report] certificate identifier, or one derived from the run (configuration, seed, trials)."""
    if fields.get("certificate"):
        return fields["certificate"]
    spec = res.spec or {}
    h = hashlib.sha256(json.dumps([spec.get("config"), spec.get("seed"), res.trials], sort_keys=True,
                                  default=str).encode()).hexdigest()[:12]
    return f"mtbudget-{spec.get('seed')}-{res.trials}-{h}"


def dcc_tree(res, tolerance_um: float | None = None, characteristic: str = "component") -> ET.ElementTree:
    """The DCC of a run (a RunResult from ``runner.replay``) as an ElementTree; refused for a run whose identification
    did not converge on more than ``outputs.MAX_NOT_CONVERGED`` of its trials (a smaller share is its warning
    statement)."""
    from .errors import IdentificationError
    from .report import no_certificate_line, too_many_not_converged

    if too_many_not_converged(res.not_converged, res.trials):
        raise IdentificationError(no_certificate_line(res.not_converged, res.trials))
    h = headline(res, tolerance_um, characteristic)
    chain = ((res.spec or {}).get("config") or {}).get("machine", "XFYZ")
    return statement_tree(h, res.points(), coverage=float(res.coverage), frame=table_frame(res),
                          identifier=certificate_id(res, h["fields"]), chain=chain,
                          method=f"Monte Carlo method, {res.trials} trials",
                          no_points="the run log holds no per-point coverage intervals",
                          more=lambda results: _features(results, res))


def posterior_dcc_tree(post, tolerance_um: float | None = None, characteristic: str = "component") -> ET.ElementTree:
    """The DCC of an a posteriori statement (:class:`mtbudget.posterior.Posterior`): the same certificate as a run's
    (:func:`statement_tree`), its kind of statement the recording and its digest, its per-point estimate, u and
    interval, its U and decision, and the chi-square test's warning where the fit fails it."""
    from .errors import IdentificationError
    from .report import no_certificate_line, posterior_headline, too_many_not_converged

    if too_many_not_converged(post.data.get("not_converged", 0), post.data["trials"]):
        raise IdentificationError(no_certificate_line(post.data["not_converged"], post.data["trials"]))
    h = posterior_headline(post, tolerance_um, characteristic)
    if not h["fields"].get("date_stated"):  # its performance date is the measurement's, never this evaluation's
        raise ConfigError(f"{post.data['statement_kind']['recording']}: recording.toml states no [report] date (the "
                          "date of the measurement), which a certificate gives as its performance date; state it, "
                          "e.g. [report] date = \"2026-11-20\"")
    p = post.data
    k = p["statement_kind"]
    ident = h["fields"].get("certificate") or (
        f"mtbudget-posterior-{k.get('points_csv_sha256') or 'nodigest'}-{p['seed']}-{p['trials']}")
    pts = p["points"]
    return statement_tree(h, pts, coverage=float(p["coverage"]), frame=bool(pts) and "frame" in pts[0],
                          identifier=ident, chain=p.get("machine", "XFYZ"),
                          method=f"Monte Carlo method around the identified errors of the recording {k['recording']} "
                                 f"(a posteriori), {p['trials']} trials, seed {p['seed']}",
                          no_points="the statement holds no per-point coverage intervals")


def statement_tree(h: dict, pts: list | None, *, coverage: float, frame: bool, identifier: str, chain: str,
                   method: str, no_points: str, more=None) -> ET.ElementTree:
    """The DCC of either kind of statement from its statement in brief ``h`` (``report.statement_in_brief``) and its
    per-point statement ``pts``: administrative data from h's fields, the statements (kind of statement, a warning
    where there is one, traceability, decision rule, decision), U per axis over the mesh and every point's estimate,
    u and coverage interval; ``more(results)`` adds results of its own (a run's features)."""
    f = h["fields"]
    country = f.get("country") or "ZZ"  # ZZ: user-assigned code of ISO 3166-1, "no country stated"
    date = f["date"]
    root = ET.Element(_d("digitalCalibrationCertificate"), {"schemaVersion": SCHEMA_VERSION})
    root.set("{http://www.w3.org/2001/XMLSchema-instance}schemaLocation", SCHEMA_LOCATION)
    adm = _sub(root, _d("administrativeData"))
    sw = _sub(_sub(adm, _d("dccSoftware")), _d("software"))
    _text(sw, "name", "mtbudget")
    _sub(sw, _d("release"), __version__)
    _sub(sw, _d("type"), "application")
    core = _sub(adm, _d("coreData"))
    _sub(core, _d("countryCodeISO3166_1"), country)
    _sub(core, _d("usedLangCodeISO639_1"), "en")
    _sub(core, _d("mandatoryLangCodeISO639_1"), "en")
    _sub(core, _d("uniqueIdentifier"), identifier)
    _sub(core, _d("beginPerformanceDate"), date)
    _sub(core, _d("endPerformanceDate"), date)
    _sub(core, _d("performanceLocation"), f.get("location") or "other")
    items = _sub(adm, _d("items"))
    item = _sub(items, _d("item"))
    _text(item, "name", f["machine"])
    ids = _sub(item, _d("identifications"))
    ident = _sub(ids, _d("identification"))
    _sub(ident, _d("issuer"), "calibrationLaboratory")
    _sub(ident, _d("value"), f"kinematic chain {chain}")
    _text(ident, "name", "machine tool configuration (ISO 10791 / ISO 230-1 axis order)")
    lab = _sub(adm, _d("calibrationLaboratory"))
    _contact(lab, "contact", f.get("laboratory"), country)
    resp = _sub(_sub(adm, _d("respPersons")), _d("respPerson"))
    _contact(resp, "person", f.get("operator"), country, strict=False)
    _sub(resp, _d("role"), "operator")
    _contact(adm, "customer", f.get("customer"), country)
    st = _sub(adm, _d("statements"))
    for name, text in (("kind of statement", h["kind_text"]),
                       *((("warning", h["warning"]),) if h.get("warning") else ()),
                       ("traceability", f.get("traceability") or NOT_STATED),
                       ("decision rule", h["rule"]), ("decision", h["decision"])):
        s = _sub(st, _d("statement"))
        _text(s, "name", name)
        d = _sub(s, _d("declaration"))
        _sub(d, _d("content"), text, lang="en")
    mres = _sub(_sub(root, _d("measurementResults")), _d("measurementResult"))
    _text(mres, "name", "error of the compensated machine tool after a volumetric verification with a laser tracker")
    desc = _sub(mres, _d("description"))
    _sub(desc, _d("content"), h["measurand"], lang="en")
    meth = _sub(_sub(mres, _d("usedMethods")), _d("usedMethod"))
    _text(meth, "name", method)
    _sub(meth, _d("norm"), "JCGM 101:2008")
    if f.get("instrument"):
        eq = _sub(_sub(mres, _d("measuringEquipments")), _d("measuringEquipment"))
        _text(eq, "name", f"laser tracker: {f['instrument']}")
    results = _sub(mres, _d("results"))
    if "U_max" in h:
        unit = DSI_UNITS.get(h["unit"], h["unit"])
        nd, p = h["decimals"], coverage
        first = _sub(results, _d("result"))
        k = h["k"]
        _text(first, "name", f"expanded uncertainty of the error after compensation over the mesh, per axis (k = {k:g})")
        data = _sub(first, _d("data"))
        u = np.array([q["u"]["value"] for q in pts])
        fw = " (workpiece (table) frame: the machine's axis with every rotary axis at zero, turning with the table)" \
            if frame else ""
        for j, a in enumerate("xyz"):
            _quantity(data, f"largest expanded uncertainty U ({h['k_text']}) of the {a} error{fw} over the mesh",
                      label=f"U_max_{a}", value=round(k * float(u[:, j].max()), nd), unit=unit, nd=nd)
            _quantity(data, f"RMS over the mesh of the expanded uncertainty U ({h['k_text']}) of the {a} error{fw}",
                      label=f"U_rms_{a}", value=round(k * float(np.sqrt((u[:, j] ** 2).mean())), nd), unit=unit, nd=nd)
        per = _sub(results, _d("result"))
        mf = "machine_frame" in pts[0]
        _text(per, "name", "error of each axis at each mesh point after compensation: estimate, standard "
                           f"uncertainty and {100 * p:g} % coverage interval (JCGM 101)" +
              (f"; x, y, z{fw}; X, Y, Z: the same error in the machine frame at the point's pose" +
               (f" ({100 * p:g} % coverage interval of every trial turned to it)" if "interval" in pts[0]["machine_frame"]
                else f" (U = {k:g}u from its standard uncertainty, the covariance turned; its coverage probability is "
                     f"the normal distribution's for k = {k:g}, assumed: the Monte Carlo gives no interval in this "
                     "frame)") if mf else
               f"; x, y, z{fw}" if fw else ""))
        lst = _sub(_sub(per, _d("data")), _d("list"))
        for q in pts:
            pl = _sub(lst, _d("list"))
            ang = q.get("angles")
            at = "" if not ang else ", " + ", ".join(sorted(ang["value"])) + " = " + ", ".join(
                f"{ang['value'][r]:.3f}" for r in sorted(ang["value"])) + f" {ang['unit']}"
            _text(pl, "name", f"point {q['point']} at x, y, z = " +
                  ", ".join(f"{v:.3f}" for v in q["nominal"]["value"]) + f" mm{at} (commanded)")
            for j, a in enumerate("xyz"):
                _quantity(pl, f"{a} error" + (" (table frame)" if fw else ""), label=f"e_{a}", value=q["mean"]["value"][j],
                          unit=unit, nd=nd, u=q["u"]["value"][j],
                          interval=(q["interval"]["low"][j], q["interval"]["high"][j]), p=p)
            if mf:
                m = q["machine_frame"]
                for j, a in enumerate("XYZ"):
                    if "interval" in m:  # an a posteriori statement turns every trial: real intervals
                        _quantity(pl, f"{a} error (machine frame at this pose)", label=f"e_machine_{a}",
                                  value=m["mean"][j], unit=unit, nd=nd, u=m["u"][j],
                                  interval=(m["interval"]["low"][j], m["interval"]["high"][j]), p=p)
                    else:  # a run: the mean and covariance turned, U = k u at the normal's p for that k, said so
                        _quantity(pl, f"{a} error (machine frame at this pose; U = {k:g}u, normal distribution "
                                      "assumed)", label=f"e_machine_{a}", value=m["mean"][j], unit=unit, nd=nd,
                                  U=k * m["u"][j], k=k, p=round(_normal_coverage(k), 4))
    else:
        r = _sub(results, _d("result"))
        _text(r, "name", "no per-point statement")
        d = _sub(r, _d("data"))
        t = _sub(d, _d("text"))
        _sub(t, _d("content"), no_points, lang="en")
    if more is not None:
        more(results)
    ET.indent(root, space=" ")
    return ET.ElementTree(root)


def _normal_coverage(k: float) -> float:
    """The coverage probability of +-k standard deviations of a normal distribution (k = 2: 0.9545)."""
    from statistics import NormalDist

    return 2.0 * NormalDist().cdf(float(k)) - 1.0


def _features(results, res):
    """The [[features]] of the run (report.md's features table): per feature its error (measured minus true, a part
    at nominal) with its standard uncertainty and coverage interval, and its decision where a tolerance is stated."""
    from .report import features_of
    from .stats import decimals_for

    feats = [f for f in features_of(res) or [] if "u" in f]
    if not feats:
        return
    r = _sub(results, _d("result"))
    from .features import frame_note

    _text(r, "name", "features probed on the compensated machine: error of each feature, measured minus true, for a "
                     "part at nominal" + frame_note(feats) + " (docs/features.md)")
    data = _sub(r, _d("data"))
    for f in feats:
        iv, dec = f["interval"], f.get("decision")
        name = f"{f['name']} ({f['kind']}): {f['measurand']}"
        if dec:
            name += f"; decision (ISO 14253-1): {dec['statement']}; rule: {dec['rule']}"
        _quantity(data, name, label=f"feature_{f['name']}", value=f["estimate"], unit=DSI_UNITS.get(f["unit"], f["unit"]),
                  nd=decimals_for(f["u"]), u=f["u"], interval=(iv["low"], iv["high"]), p=iv["coverage"])
    _feature_points(results, feats)


def _feature_points(results, feats):
    """The probed points of every feature, part of its measurand: per point the commanded position of the linear axes
    (mm) and, on a five-axis machine, the commanded angle of each rotary axis (deg) and the nominal point on the part
    in the workpiece (table) frame (mm), as quantities without uncertainty (they define the measurand)."""
    from .features import probed_points

    feats = [f for f in feats if "points" in f]
    if not feats:
        return
    r = _sub(results, _d("result"))
    _text(r, "name", "probed points of each feature (part of its measurand): commanded positions of the linear axes "
                     "and commanded angles of the rotary axes, in the order of probing")
    data = _sub(r, _d("data"))
    for f in feats:
        fl = _sub(data, _d("list"))
        _text(fl, "name", f"{f['name']} ({f['kind']}): {len(f['points']['value'])} probed points")
        for j, (p, ang, nom) in enumerate(probed_points(f)):
            pl = _sub(fl, _d("list"))
            _text(pl, "name", f"point {j + 1}")
            for a, v in zip("XYZ", p):
                _quantity(pl, f"commanded {a} position (machine axis)", label=f"commanded_{a}", value=v,
                          unit=DSI_UNITS["mm"], nd=4)
            for a, v in ang.items():
                _quantity(pl, f"commanded {a} angle (rotary axis)", label=f"commanded_{a}", value=v,
                          unit=DSI_UNITS["deg"], nd=4)
            if nom is not None:
                nf = (f.get("nominal_points") or {}).get("frame", "workpiece (table) frame")  # a head-side: machine
                for a, v in zip("xyz", nom):
                    _quantity(pl, f"nominal {a} of the point on the part, {nf}", label=f"nominal_{a}",
                              value=v, unit=DSI_UNITS["mm"], nd=4)


def write_dcc(res, path, tolerance_um: float | None = None, characteristic: str = "component") -> Path:
    """Write the DCC of a run, or of an a posteriori statement (:class:`mtbudget.posterior.Posterior`), to ``path``
    (UTF-8 XML); returns the path."""
    from .posterior import Posterior

    path = Path(path)
    tree = (posterior_dcc_tree if isinstance(res, Posterior) else dcc_tree)(res, tolerance_um, characteristic)
    tree.write(path, encoding="UTF-8", xml_declaration=True)
    return path
