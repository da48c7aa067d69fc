"""Built-in compensation-table exporters (hook ``mtbudget_register_exporters``).

* ``neutral-csv`` / ``neutral-json``: every identified error function under its ISO 230-1
  name on the user's grid, the squareness errors, the per-axis positioning tables (mean,
  forward, reverse) and the reversal, each entry with its standard uncertainty, units and
  the sign convention stated in the file.
* ``linuxcnc``: one LinuxCNC joint compensation file per axis, ``COMP_FILE_TYPE = 1``
  (nominal, forward trim, reverse trim in machine units), LinuxCNC docs
  docs/src/config/ini-config.adoc ``[JOINT_n]`` COMP_FILE / COMP_FILE_TYPE, loader
  src/emc/motion/usrmotintf.cc ``usrmotLoadComp``, applied in src/emc/motion/control.c.
* ``beckhoff-lsec``: one Beckhoff TwinCAT CNC (ISG kernel) compensation value list per axis
  with bilateral leadscrew error compensation (``kw.ssfk.*``, P-COMP-00017..00025).
* ``siemens-840d``: SINUMERIK 840D sl LEC tables (``$AA_ENC_COMP``) and sag / cross compensation
  tables (``$AN_CEC``), two programs ``FILE_eec.ini`` and ``FILE_cec.ini``; ``siemens-828d`` the same within
  the 828D's 8 tables of 200 points (the reversal tables, no cross tables).  The ``$AN_CEC`` sign is the
  user's explicit choice (``table.options["siemens_cec_sign"]``, ``--siemens-cec-sign``).
* ``heidenhain-tnc``: HEIDENHAIN nonlinear axis error compensation (MANUALplus 620 layout), ``FILE_x.com``
  ... (always ``.com``), the assignment ``FILE.cma`` and ``FILE_notes.txt`` (activation, unverified points).

docs/compensation.md states each format's grid, units, sign, extrapolation and backlash
conventions with their sources.  Every writer here uses only the public fields of
:class:`mtbudget.compensate.CompensationTable`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mtbudget.contracts import Exporter
from mtbudget.hookspecs import hookimpl

_AXIS_NUMBER = {"x": 1, "y": 2, "z": 3}


def _zero(table, a) -> str:
    """Where axis ``a``'s tables are zero, in words: its reference point, or the table end nearest it."""
    t, ref = table.axes[a], table.reference_point.get(a, 0.0)
    if t.zero_at == ref:
        return f"zero at the reference point {a.upper()} = {ref:g} mm"
    return f"zero at {a.upper()} = {t.zero_at:g} mm, the table end nearest the reference point {ref:g} mm (held there)"


def _f(v, nd=4):
    return "" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


class NeutralCsv(Exporter):
    name = "neutral-csv"
    description = "every ISO 230-1 error function on the grid, positioning tables and reversal, with u (CSV)"
    suffix = ".csv"
    convention = ("mtbudget's own neutral table (docs/compensation.md, 'The neutral table'): ISO 230-1 names and "
                  "sign (tool relative to workpiece, error = actual - nominal), um / urad / mm, k = 1 uncertainties")

    def write(self, table, path):
        path = Path(path)
        head = [f"# mtbudget compensation table of recording {table.recording!r}, machine {table.machine}, "
                f"grid step {table.step:g} mm"]
        head += [f"# {k}: {v}" for k, v in table.conventions.items()]
        rows = ["kind,iso_name,mtbudget_name,axis,position_mm,value,u,unit,identifiable"]
        for f in table.functions:
            for p, v, u in zip(f.positions, f.value, f.u):
                rows.append(f"error_function,{f.iso},{f.internal},{f.axis},{p:.4f},{_f(v)},{_f(u)},{f.unit},"
                            f"{int(f.identifiable)}")
        for s in table.squareness:
            rows.append(f"squareness,{s.iso},{s.internal},,,{_f(s.value)},{_f(s.u)},urad,{int(s.identifiable)}")
        for a, t in table.axes.items():
            pos = f"E{a.upper()}{a.upper()}"
            for kind, vals, us in (("positioning_mean", t.deviation, t.u), ("positioning_forward", t.forward, t.u_directional),
                                   ("positioning_reverse", t.reverse, t.u_directional)):
                for p, v, u in zip(t.positions, vals, us):
                    rows.append(f"{kind},{pos},line,{a},{p:.4f},{_f(v)},{_f(u)},um,1")
            rows.append(f"reversal,B,reversal,{a},,{_f(t.reversal)},{_f(t.u_reversal)},um,1")
        for c in getattr(table, "cross", {}).values():
            for p, v, u in zip(c.positions, c.deviation, c.u):
                rows.append(f"cross,{c.iso},line,{c.axis},{p:.4f},{_f(v)},{_f(u)},um,1")
        for r in getattr(table, "rotary", []):  # five-axis: ISO 230-7 location and zero errors (datum: no u)
            rows.append(f"rotary_{r['kind']},{r['iso']},{r['mtbudget']},{r['axis'].lower()},,{_f(r['value'])},"
                        f"{_f(r['u'])},{r['unit']},{int(r['identifiable'])}")
        path.write_text("\n".join(head + rows) + "\n")
        return [path]


class NeutralJson(Exporter):
    name = "neutral-json"
    description = "the same neutral table as one JSON document, with the ISO 230-2 figures"
    suffix = ".json"
    convention = NeutralCsv.convention

    def write(self, table, path):
        path = Path(path)
        path.write_text(json.dumps(table.to_dict(), indent=1) + "\n")
        return [path]


class LinuxCnc(Exporter):
    name = "linuxcnc"
    description = "LinuxCNC joint compensation files, COMP_FILE_TYPE = 1 (nominal, forward trim, reverse trim; mm)"
    suffix = ".comp"
    per_axis = True
    max_entries = 256  # "Currently the limit inside LinuxCNC is for 256 triplets per joint"
    max_entries_source = "LinuxCNC: 256 triplets per joint, INI configuration COMP_FILE"
    convention = ("LinuxCNC INI configuration, [JOINT_n] COMP_FILE and COMP_FILE_TYPE (docs/src/config/ini-config.adoc); "
                  "loader usrmotLoadComp (src/emc/motion/usrmotintf.cc), use in compute_screw_comp and motor_pos_cmd "
                  "(src/emc/motion/control.c): trims in machine units added to the joint command, linear between "
                  "nominals, end values held beyond the table, forward while the commanded velocity is > 0")

    def write(self, table, path):
        written = []
        for j, (a, t) in enumerate(table.axes.items()):
            p = self.axis_path(path, a)
            # trim = nominal - actual = -(deviation): what the controller adds so the axis lands on nominal.
            # The notes come AFTER the table: usrmotLoadComp stops reading at the first line that is not three
            # numbers, so a header would empty the table (tests/test_controller_linuxcnc.py loads these files).
            fwd, rev = -t.forward * 1e-3, -t.reverse * 1e-3
            rows = "".join(f"{n:.6f} {f:.6f} {r:.6f}\n" for n, f, r in zip(t.positions, fwd, rev))
            notes = [f"mtbudget: joint compensation of axis {a.upper()} from recording {table.recording!r}, machine units mm",
                     "columns: nominal, forward trim, reverse trim (COMP_FILE_TYPE = 1); trim = -(ISO 230-2 deviation)",
                     f"{_zero(table, a)}; the table covers {t.positions[0]:g}..{t.positions[-1]:g} mm "
                     "and its end values hold beyond",
                     f"activate in the INI file, in the section of the joint that drives axis {a.upper()} (below: "
                     f"joint {j}, the table's axis order, as trivkins numbers the joints; a five-axis kinematics module "
                     "(xyzac-trt-kins ...) numbers them as its documentation says):",
                     f"  [JOINT_{j}] COMP_FILE = {p.name}   COMP_FILE_TYPE = 1   BACKLASH = 0 (the reversal is in the "
                     "forward/reverse trims; [TRAJ] LINEAR_UNITS = mm)",
                     "restart LinuxCNC and home the joint: the trims are applied once it is homed (src/emc/motion/control.c)",
                     "these lines come after the table because LinuxCNC stops reading at the first line that is not "
                     "three numbers"]
            p.write_text(rows + "".join(f"# {n}\n" for n in notes))
            written.append(p)
        return written


class BeckhoffLsec(Exporter):
    name = "beckhoff-lsec"
    description = "Beckhoff TwinCAT CNC compensation value lists, bilateral leadscrew error compensation (0.1 um)"
    suffix = ".lis"
    per_axis = True
    max_entries = 1499  # kw_nr_max must be smaller than kw.ssfk.max_points (P-COMP-00059, default 1500)
    max_entries_source = "TwinCAT CNC: kw_nr_max must be smaller than kw.ssfk.max_points, P-COMP-00059, default 1500"
    convention = ("Beckhoff Information System, TwinCAT CNC axis compensation: leadscrew error compensation "
                  "kw.ssfk.* (P-COMP-00017 unit, -00018 interval, -00019 kw_startpos, -00020 kw_nr_max, -00021 "
                  "bilateral, -00023 table[i].pos, -00024 table[i].neg, -00025 table[i].setpoint) and its example "
                  "list: values are actual - setpoint in 0.1 um, linearly interpolated; comments '# ' per line")

    def limit_error(self, table):
        """One line naming the limit a table exceeds, or None (SGN16 values, TwinCAT CNC's older builds)."""
        for a, t in table.axes.items():
            big = float(np.abs(np.concatenate([t.forward, t.reverse])).max(initial=0.0))
            if big * 10 > 32767:
                return (f"axis {a.upper()}: a compensation value of {big:.1f} um exceeds the SGN16 range of "
                        "kw.ssfk.table[i].pos/neg (P-COMP-00023/-00024: |value| < 32767 x 0.1 um = 3276.7 um)")
        return None

    def write(self, table, path):
        written = []
        for a, t in table.axes.items():
            p = self.axis_path(path, a)
            pos = np.rint(t.forward * 10).astype(int)  # um -> 0.1 um, actual - setpoint moving in +
            neg = np.rint(t.reverse * 10).astype(int)
            setp = np.rint(t.positions * 1e4).astype(int)  # mm -> 0.1 um
            lines = [f"# mtbudget: leadscrew error compensation of axis {a.upper()} from recording {table.recording!r}",
                     "# for Beckhoff TwinCAT CNC (the ISG kernel, TF5200) only: not for TwinCAT NC PTP, whose "
                     "compensation is additive, the opposite sign",
                     "# values = actual - setpoint (ISO 230-2 deviation) in 0.1 um; the CNC subtracts them",
                     f"# on the line {', '.join(f'{b} = {v:g} mm' for b, v in t.reference.items())}; {_zero(table, a)}",
                     "# set kopf.log_achs_nr to the logical axis number of your configuration",
                     "# activate: enter this list for the axis in the start-up list, set lr_param.ssfk = 1 (P-AXIS-00175) "
                     "in the axis parameter list, set the axis' own backlash compensation to 0 (the reversal is in "
                     "pos/neg), restart; the compensation acts once the axis is homed",
                     f"kopf.log_achs_nr                {_AXIS_NUMBER[a]}",
                     f"kopf.log_achs_name              {a.upper()}",
                     "kw.ssfk.interval                0",
                     f"kw.ssfk.kw_startpos             {setp[0]}",
                     f"kw.ssfk.kw_nr_max               {len(setp)}",
                     "kw.ssfk.unit                    1",
                     "kw.ssfk.bilateral               1"]
            lines += [f"kw.ssfk.table[{i}].setpoint{'':<6}{v}" for i, v in enumerate(setp)]
            lines += [f"kw.ssfk.table[{i}].pos{'':<11}{v}" for i, v in enumerate(pos)]
            lines += [f"kw.ssfk.table[{i}].neg{'':<11}{v}" for i, v in enumerate(neg)]
            p.write_text("\n".join(lines) + "\n")
            written.append(p)
        return written


_SIEMENS_AXIS = {"x": "AX1", "y": "AX2", "z": "AX3"}


def _steps_off(positions) -> bool:
    """Whether positions are not MIN + N STEP on whole micrometres (so printed with three decimals they would not
    give an integer (MAX - MIN) / STEP)."""
    um = np.rint(np.asarray(positions) * 1e3)
    return bool(np.any(np.abs(np.asarray(positions) * 1e3 - um) > 1e-6) or np.ptp(np.diff(um)) != 0)


def _equidistant(positions, what):
    d = np.diff(positions)
    if len(d) == 0 or np.ptp(d) > 1e-6 * max(1.0, abs(d[0])):
        raise ValueError(f"{what}: the grid is not equidistant (step MIN..MAX tables need one spacing)")
    return float(d[0])


class Siemens840d(Exporter):
    name = "siemens-840d"
    description = ("SINUMERIK 840D sl: LEC tables $AA_ENC_COMP (mean positioning) and sag / cross compensation "
                   "$AN_CEC (reversal by direction, straightness and squareness of each line); mm; needs "
                   "--siemens-cec-sign")
    suffix = ".ini"
    control = "SINUMERIK 840D sl"
    cross = True  # write the cross (sag) tables
    max_cec_tables = None  # 840D: set by MD18342 (its maximum not found in the pages consulted): not enforced
    max_cec_points = None
    convention = ("SINUMERIK 840D sl Function Manual Extended Functions, K3 Compensation: interpolatory compensation, "
                  "LEC/MSEC ($AA_ENC_COMP[0,N,AXi], _STEP, _MIN, _MAX, _IS_MODULO; example %_N_AX_EEC_INI, values in mm) "
                  "and sag compensation ($AN_CEC[t,N], _INPUT_AXIS, _OUTPUT_AXIS, _STEP, _MIN, _MAX, _DIRECTION, "
                  "_MULT_BY_TABLE, _IS_MODULO; first / last value held beyond MIN / MAX; MD38000, MD18342 points); "
                  "LEC sign from the SINUMERIK 808D LEC manual: a positive value moves the axis in the negative direction; "
                  "the $AN_CEC sign is not stated in any source found: --siemens-cec-sign chooses it")

    def cec_tables(self, table) -> list:
        """(input axis, output axis, positions mm, deviation um, direction, what) of every $AN_CEC table written."""
        tables = []
        for a, t in table.axes.items():
            n = len(t.positions)
            tables.append((a, a, t.positions, np.full(n, 0.5 * t.reversal), 1, f"reversal of {a.upper()}, + direction: +B/2"))
            tables.append((a, a, t.positions, np.full(n, -0.5 * t.reversal), -1, f"reversal of {a.upper()}, - direction: -B/2"))
        if self.cross:
            for c in table.cross.values():
                tables.append((c.axis, c.output, c.positions, c.deviation, 0,
                               f"{c.iso}: deviation in {c.output.upper()} along {c.axis.upper()}"))
        return tables

    def limit_error(self, table):
        """One line naming the first limit of the control the table exceeds, or None."""
        if table.options.get("siemens_cec_sign") not in ("error", "correction"):
            return ("needs --siemens-cec-sign error|correction: no Siemens text found states whether a $AN_CEC entry is "
                    "the measured error or the correction; docs/compensation.md gives a one-value test on the machine")
        tables = self.cec_tables(table)
        if self.max_cec_tables is not None and len(tables) > self.max_cec_tables:
            return (f"{len(tables)} $AN_CEC tables; the {self.control} has at most {self.max_cec_tables} (sag "
                    f"compensation, multi-dimensional: {self.max_cec_tables} tables of {self.max_cec_points} points)")
        for k, (a, b, pos, *_rest) in enumerate(tables):
            if self.max_cec_points is not None and len(pos) > self.max_cec_points:
                return (f"--step {table.step:g} mm gives {len(pos)} points in $AN_CEC table {k} ({a.upper()}); the "
                        f"{self.control} takes at most {self.max_cec_points} per table: use a larger --step")
        for a, t in table.axes.items():
            if _steps_off(t.positions):
                return f"axis {a.upper()}: the grid is not equidistant on whole micrometres (MIN + N STEP = MAX)"
        return None

    def write(self, table, path):
        path = Path(path)
        stem, suf = path.stem, path.suffix or self.suffix
        eec, cec = path.with_name(f"{stem}_eec{suf}"), path.with_name(f"{stem}_cec{suf}")
        sign = table.options["siemens_cec_sign"]
        cec_factor = 1.0 if sign == "error" else -1.0  # entry = error, or entry = correction = -error
        head = [f"; mtbudget: compensation of recording {table.recording!r} ({table.machine}) for the {self.control}; "
                "values and positions in mm",
                "; machine axes AX1, AX2, AX3 = X, Y, Z: rename them to your configuration",
                *[f"; {_zero(table, a)}" for a in table.axes],
                "; machine-data names as in the K3 function manual (840D sl 03/2013); check them in your edition"]
        lines = ["%_N_AX_EEC_INI", *head,
                 "; LEC: mean bidirectional positioning deviation on each axis' reference line",
                 "; sign: value = measured error (actual - nominal): a positive value moves the axis in - (808D LEC manual)",
                 "; activate: 1. MD32700 $MA_ENC_COMP_ENABLE[0,AXi] = 0 while loading (an active table is write-protected)",
                 ";           2. MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0,AXi] >= the points below, power on (memory is "
                 "reorganised: back up first)",
                 ";           3. run this program, then MD32700 = 1 and NEWCONF / reset; the LEC acts once the axis is "
                 "referenced",
                 "CHANDATA(1)"]
        for a, t in table.axes.items():
            ax = _SIEMENS_AXIS[a]
            step = _equidistant(t.positions, f"axis {a}")
            lines.append(f"; axis {a.upper()}: {len(t.positions)} interpolation points, set MD38000 "
                         f"$MA_MM_ENC_COMP_MAX_POINTS[0,{ax}] >= {len(t.positions)}")
            lines += [f"$AA_ENC_COMP[0,{i},{ax}]={v * 1e-3:.6f}" for i, v in enumerate(t.deviation)]
            lines += [f"$AA_ENC_COMP_STEP[0,{ax}]={step:.3f}", f"$AA_ENC_COMP_MIN[0,{ax}]={t.positions[0]:.3f}",
                      f"$AA_ENC_COMP_MAX[0,{ax}]={t.positions[-1]:.3f}", f"$AA_ENC_COMP_IS_MODULO[0,{ax}]=0"]
        lines.append("M17")
        eec.write_text("\n".join(lines) + "\n")

        tables = self.cec_tables(table)
        what = ("tables 0..5: reversal, one table per direction of travel of the same axis ($AN_CEC_DIRECTION = 1 / -1)"
                + ("; then the cross (sag) tables: output axis as a function of the input axis' setpoint" if self.cross
                   else f"; the cross (sag) tables are left out: the {self.control} has {self.max_cec_tables} tables "
                        "and the reversal takes six (neutral-json carries them)"))
        lines = ["%_N_NC_CEC_INI", *head, "; " + what,
                 f"; SIGN (--siemens-cec-sign {sign}): " +
                 ("entry = measured error (actual - nominal), as the LEC: a positive entry moves the output axis in -"
                  if sign == "error" else
                  "entry = correction = nominal - actual, added to the output axis' setpoint: a positive entry moves it in +"),
                 "; NO SIEMENS TEXT FOUND STATES THE $AN_CEC SIGN: test it before use (docs/compensation.md): load one "
                 "table with every entry +0.010, input = output = one axis, enable it, stop the axis at a position and "
                 "measure it (dial gauge or the service display's sag value): moved 10 um in - => 'error'; in + => "
                 "'correction'",
                 "; activate: 1. MD18342 $MN_MM_CEC_MAX_POINTS[t] >= the points below (840D; the 828D has 8 tables of "
                 "200 points, fixed), power on",
                 ";           2. SD41300 $SN_CEC_TABLE_ENABLE[t] = 0 while loading, run this program",
                 ";           3. SD41300 $SN_CEC_TABLE_ENABLE[t] = 1, SD41310 $SN_CEC_TABLE_WEIGHT[t] = 1.0, "
                 "MD32710 $MA_CEC_ENABLE[0,AXi] = 1 for each output axis, NEWCONF",
                 ";           4. MD32450 $MA_BACKLASH[0,AXi] = 0: the reversal is in tables 0..5, a backlash value "
                 "would compensate it twice",
                 "CHANDATA(1)"]
        for k, (a, b, pos, val, direction, desc) in enumerate(tables):
            step = _equidistant(pos, f"table {k}")
            lines.append(f"; table {k}: {desc}; set MD18342 $MN_MM_CEC_MAX_POINTS[{k}] >= {len(pos)}")
            lines += [f"$AN_CEC[{k},{i}]={cec_factor * v * 1e-3:.6f}" for i, v in enumerate(val)]
            lines += [f"$AN_CEC_INPUT_AXIS[{k}]=({_SIEMENS_AXIS[a]})", f"$AN_CEC_OUTPUT_AXIS[{k}]=({_SIEMENS_AXIS[b]})",
                      f"$AN_CEC_STEP[{k}]={step:.3f}", f"$AN_CEC_MIN[{k}]={pos[0]:.3f}", f"$AN_CEC_MAX[{k}]={pos[-1]:.3f}",
                      f"$AN_CEC_DIRECTION[{k}]={direction}", f"$AN_CEC_MULT_BY_TABLE[{k}]=0", f"$AN_CEC_IS_MODULO[{k}]=0"]
        lines.append("M17")
        cec.write_text("\n".join(lines) + "\n")
        return [eec, cec]


class Siemens828d(Siemens840d):
    name = "siemens-828d"
    description = ("SINUMERIK 828D: LEC tables $AA_ENC_COMP and the reversal in six $AN_CEC direction tables (the 828D "
                   "has 8 tables of 200 points: no room for the six cross tables); mm; needs --siemens-cec-sign")
    control = "SINUMERIK 828D"
    cross = False
    max_cec_tables = 8  # K3 function manual 03/2013, 4.4.4.3: "eight tables each with 200 interpolation points"
    max_cec_points = 200
    convention = Siemens840d.convention + ("; 828D: 'immediately eight tables each with 200 interpolation points per "
                                           "table ... This cannot be extended!' (K3, 03/2013, 4.4.4.3)")


class HeidenhainTnc(Exporter):
    name = "heidenhain-tnc"
    description = ("HEIDENHAIN nonlinear axis error compensation in the layout of the MANUALplus 620 technical manual "
                   "(TNC 4xx and iTNC 530 differ): one .COM table per axis (its positioning, BACKLASH for the negative "
                   "direction, the other axes' sag on its line), the .CMA assignment and a notes file; mm")
    suffix = ".com"
    per_axis = True
    max_entries = 256  # TNC 407/415/425 technical manual, module 9095: "more than 256 entries" is an error
    max_entries_source = "HEIDENHAIN: at most 256 entries per .COM table, module 9095"
    convention = ("HEIDENHAIN technical manuals, nonlinear axis error compensation: TNC 407/415/425 (243 020), "
                  "section 'Non-linear axis error compensation' (.COM tables assigned per axis in a .CMA file, one line "
                  "active, at most 256 entries, sign of the linear compensation: 'positive when the table travels too "
                  "far'); MANUALplus 620 (2012), 'Entering compensation values' and 'Assigning the compensation value "
                  "tables' (AXISPOS from the machine datum, a column per dependent axis, BACKLASH = values measured in "
                  "the negative direction, ACTIVE '*')")

    def axis_path(self, path, axis: str):
        """``FILE_x.com`` whatever suffix ``--out`` has: the .CMA names the tables by their .COM type."""
        path = Path(path)
        return path.with_name(f"{path.stem}_{axis}.com")

    def write(self, table, path):
        path = Path(path)
        written = []
        cma_cols = {}
        for a, t in table.axes.items():
            p = self.axis_path(path, a)
            cols = {a.upper(): t.forward}
            for c in table.cross.values():
                if c.axis == a:
                    cols[c.output.upper()] = c.deviation
            names = ["NR", "AXISPOS", *sorted(cols), "BACKLASH"]
            lines = [f"BEGIN {p.name.upper()} MM", "  ".join(f"{n:<12}" for n in names).rstrip()]
            for i, pos in enumerate(t.positions):
                vals = [f"{i:<12}", f"{pos:<+12.4f}"] + [f"{cols[n][i] * 1e-3:<+12.4f}" for n in sorted(cols)] + \
                    [f"{t.reverse[i] * 1e-3:<+12.4f}"]
                lines.append("  ".join(vals).rstrip())
            lines.append("[END]")
            p.write_text("\n".join(lines) + "\n")
            written.append(p)
            cma_cols[a.upper()] = p.name.upper()
        cma = path.with_suffix(".cma")
        head = ["NR", *cma_cols, "ACTIVE"]
        cma.write_text("\n".join([f"BEGIN {cma.name.upper()}", "  ".join(f"{n:<16}" for n in head).rstrip(),
                                   "  ".join(f"{v:<16}" for v in ["0", *cma_cols.values(), "*"]).rstrip(),
                                   "[END]"]) + "\n")
        written.append(cma)
        notes = path.with_name(f"{path.stem}_notes.txt")
        notes.write_text("\n".join([
            f"mtbudget: HEIDENHAIN nonlinear axis error compensation of recording {table.recording!r} ({table.machine})",
            "control family: the layout of the MANUALplus 620 technical manual (2012): .COM tables with AXISPOS from "
            "the machine datum, a column per compensated axis, BACKLASH, assigned in a .CMA; TNC 4xx and iTNC 530 "
            "use another layout; other controls unverified",
            f"files: {', '.join(cma_cols.values())} and {cma.name.upper()} (one line, active '*')",
            "values: the measured error (actual - nominal, mm), as the linear compensation's sign ('positive when the "
            "axis travels too far', TNC 407/415/425 technical manual); for the nonlinear tables UNVERIFIED",
            "BACKLASH column: the deviation measured moving in the negative direction (our reading of the MANUALplus 620 "
            "manual: 'enter the compensation values measured in the negative direction of traverse in the BACKLASH "
            "column'); UNVERIFIED whether the control takes it as that value or as the difference to the axis column",
            "reference: " + "; ".join(_zero(table, a) for a in table.axes) + " (AXISPOS counts from the machine datum)",
            "activate: copy the .COM and .CMA files to the control's table folder, enter the .CMA as the active "
            "assignment, set the axis' backlash compensation MP_backLash to 0 (the reversal is in BACKLASH: a value "
            "there compensates it twice), restart; check one axis with a single test value before use",
            "sign test: set one entry of an axis column to +0.010 mm at a position P, move there: if the axis "
            "(measured) moves 10 um in - relative to before, entries are errors, as written; if in +, negate the tables",
        ]) + "\n")
        written.append(notes)
        return written


@hookimpl
def mtbudget_register_exporters(register):
    for cls in (NeutralCsv, NeutralJson, LinuxCnc, BeckhoffLsec, Siemens840d, Siemens828d, HeidenhainTnc):
        register(cls())
