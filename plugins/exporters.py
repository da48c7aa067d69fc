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
  tables (``$AN_CEC``), two programs ``FILE_eec.ini`` and ``FILE_cec.ini``.
* ``heidenhain-tnc``: HEIDENHAIN TNC nonlinear axis error compensation, ``FILE_x.com`` ... and
  the assignment ``FILE.cma``.

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
    convention = ("LinuxCNC INI configuration, [JOINT_n] COMP_FILE and COMP_FILE_TYPE (docs/src/config/ini-config.adoc); "
                  "loader usrmotLoadComp (src/emc/motion/usrmotintf.cc), use in compute_screw_comp and motor_pos_cmd "
                  "(src/emc/motion/control.c): trims in machine units added to the joint command, linear between "
                  "nominals, end values held beyond the table, forward while the commanded velocity is > 0")

    def write(self, table, path):
        written = []
        for a, t in table.axes.items():
            p = self.axis_path(path, a)
            # trim = nominal - actual = -(deviation): what the controller adds so the axis lands on nominal.
            # No header or comment: the loader stops reading at the first line that is not three numbers.
            fwd, rev = -t.forward * 1e-3, -t.reverse * 1e-3
            p.write_text("".join(f"{n:.6f} {f:.6f} {r:.6f}\n" for n, f, r in zip(t.positions, fwd, rev)))
            written.append(p)
        return written


class BeckhoffLsec(Exporter):
    name = "beckhoff-lsec"
    description = "Beckhoff TwinCAT CNC compensation value lists, bilateral leadscrew error compensation (0.1 um)"
    suffix = ".lis"
    per_axis = True
    max_entries = 1500  # P-COMP-00059 default (kw.ssfk.max_points)
    convention = ("Beckhoff Information System, TwinCAT CNC axis compensation: leadscrew error compensation "
                  "kw.ssfk.* (P-COMP-00017 unit, -00018 interval, -00019 kw_startpos, -00020 kw_nr_max, -00021 "
                  "bilateral, -00023 table[i].pos, -00024 table[i].neg, -00025 table[i].setpoint) and its example "
                  "list: values are actual - setpoint in 0.1 um, linearly interpolated; comments '# ' per line")

    def write(self, table, path):
        written = []
        for a, t in table.axes.items():
            p = self.axis_path(path, a)
            pos = np.rint(t.forward * 10).astype(int)  # um -> 0.1 um, actual - setpoint moving in +
            neg = np.rint(t.reverse * 10).astype(int)
            setp = np.rint(t.positions * 1e4).astype(int)  # mm -> 0.1 um
            if np.abs(np.concatenate([pos, neg])).max(initial=0) > 32767:
                raise ValueError(f"axis {a}: a compensation value exceeds the SGN16 range of kw.ssfk.table[i].pos/neg")
            lines = [f"# mtbudget: leadscrew error compensation of axis {a.upper()} from recording {table.recording!r}",
                     "# values = actual - setpoint (ISO 230-2 deviation) in 0.1 um; the CNC subtracts them",
                     f"# on the line {', '.join(f'{b} = {v:g} mm' for b, v in t.reference.items())}; zero at the first "
                     "setpoint; set kopf.log_achs_nr to the logical axis number of your configuration",
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


def _equidistant(positions, what):
    d = np.diff(positions)
    if len(d) == 0 or np.ptp(d) > 1e-6 * max(1.0, abs(d[0])):
        raise ValueError(f"{what}: the grid is not equidistant (step MIN..MAX tables need one spacing)")
    return float(d[0])


class Siemens840d(Exporter):
    name = "siemens-840d"
    description = ("SINUMERIK 840D sl: LEC tables $AA_ENC_COMP (mean positioning) and sag / cross compensation "
                   "$AN_CEC (reversal by direction, straightness and squareness of each line); mm")
    suffix = ".ini"
    convention = ("SINUMERIK 840D sl Function Manual Extended Functions, K3 Compensation: interpolatory compensation, "
                  "LEC/MSEC ($AA_ENC_COMP[0,N,AXi], _STEP, _MIN, _MAX, _IS_MODULO; example %_N_AX_EEC_INI, values in mm) "
                  "and sag compensation ($AN_CEC[t,N], _INPUT_AXIS, _OUTPUT_AXIS, _STEP, _MIN, _MAX, _DIRECTION, "
                  "_MULT_BY_TABLE, _IS_MODULO; first / last value held beyond MIN / MAX; MD38000, MD18342 points); "
                  "sign from the SINUMERIK 808D LEC manual: a positive value moves the axis in the negative direction")

    def write(self, table, path):
        path = Path(path)
        stem, suf = path.stem, path.suffix or self.suffix
        eec, cec = path.with_name(f"{stem}_eec{suf}"), path.with_name(f"{stem}_cec{suf}")
        head = [f"; mtbudget: compensation of recording {table.recording!r} ({table.machine}); values in mm",
                "; value = measured error (actual - nominal, tool relative to workpiece): a positive value moves the "
                "axis in the negative direction",
                "; machine axes AX1, AX2, AX3 = X, Y, Z: rename them to your configuration",
                "; VERIFY THE SIGN ON THE MACHINE before use: load one small test value and check the direction the axis "
                "moves (the sag table sign is not documented in a source mtbudget could check, docs/compensation.md)"]
        lines = ["%_N_AX_EEC_INI", *head,
                 "; LEC: mean bidirectional positioning deviation on each axis' reference line, zero at MIN",
                 "CHANDATA(1)"]
        for a, t in table.axes.items():
            ax = _SIEMENS_AXIS[a]
            step = _equidistant(t.positions, f"axis {a}")
            lines.append(f"; axis {a.upper()}: {len(t.positions)} interpolation points, set MD38000 "
                         f"$MA_MM_ENC_COMP_MAX_POINTS[0,{ax}] >= {len(t.positions)}")
            lines += [f"$AA_ENC_COMP[0,{i},{ax}]={v * 1e-3:.6f}" for i, v in enumerate(t.deviation)]
            lines += [f"$AA_ENC_COMP_STEP[0,{ax}]={step:.6f}", f"$AA_ENC_COMP_MIN[0,{ax}]={t.positions[0]:.6f}",
                      f"$AA_ENC_COMP_MAX[0,{ax}]={t.positions[-1]:.6f}", f"$AA_ENC_COMP_IS_MODULO[0,{ax}]=0"]
        lines.append("M17")
        eec.write_text("\n".join(lines) + "\n")

        lines = ["%_N_NC_CEC_INI", *head,
                 "; tables 0..5: reversal, one table per direction of travel of the same axis ($AN_CEC_DIRECTION = 1 / -1)",
                 "; then the cross (sag) tables: output axis as a function of the input axis' setpoint"]
        tables = []
        for a, t in table.axes.items():
            n = len(t.positions)
            tables.append((a, a, t.positions, np.full(n, 0.5 * t.reversal), 1, f"reversal of {a.upper()}, + direction: +B/2"))
            tables.append((a, a, t.positions, np.full(n, -0.5 * t.reversal), -1, f"reversal of {a.upper()}, - direction: -B/2"))
        for c in table.cross.values():
            tables.append((c.axis, c.output, c.positions, c.deviation, 0,
                           f"{c.iso}: deviation in {c.output.upper()} along {c.axis.upper()}"))
        for k, (a, b, pos, val, direction, what) in enumerate(tables):
            step = _equidistant(pos, f"table {k}")
            lines.append(f"; table {k}: {what}; set MD18342 $MN_MM_CEC_MAX_POINTS[{k}] >= {len(pos)}")
            lines += [f"$AN_CEC[{k},{i}]={v * 1e-3:.6f}" for i, v in enumerate(val)]
            lines += [f"$AN_CEC_INPUT_AXIS[{k}]=({_SIEMENS_AXIS[a]})", f"$AN_CEC_OUTPUT_AXIS[{k}]=({_SIEMENS_AXIS[b]})",
                      f"$AN_CEC_STEP[{k}]={step:.6f}", f"$AN_CEC_MIN[{k}]={pos[0]:.6f}", f"$AN_CEC_MAX[{k}]={pos[-1]:.6f}",
                      f"$AN_CEC_DIRECTION[{k}]={direction}", f"$AN_CEC_MULT_BY_TABLE[{k}]=0", f"$AN_CEC_IS_MODULO[{k}]=0"]
        lines.append("M17")
        cec.write_text("\n".join(lines) + "\n")
        return [eec, cec]


class HeidenhainTnc(Exporter):
    name = "heidenhain-tnc"
    description = ("HEIDENHAIN TNC nonlinear axis error compensation: one .COM table per axis (its positioning, "
                   "BACKLASH for the negative direction, the other axes' sag on its line) and the .CMA assignment; mm")
    suffix = ".com"
    per_axis = True
    max_entries = 256  # TNC 407/415/425 technical manual, module 9095: "more than 256 entries" is an error
    convention = ("HEIDENHAIN technical manuals, nonlinear axis error compensation: TNC 407/415/425 (243 020), "
                  "section 'Non-linear axis error compensation' (.COM tables assigned per axis in a .CMA file, one line "
                  "active, at most 256 entries, sign of the linear compensation: 'positive when the table travels too "
                  "far'); MANUALplus 620 (2012), 'Entering compensation values' and 'Assigning the compensation value "
                  "tables' (AXISPOS from the machine datum, a column per dependent axis, BACKLASH = values measured in "
                  "the negative direction, ACTIVE '*')")

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
        return written


@hookimpl
def mtbudget_register_exporters(register):
    for cls in (NeutralCsv, NeutralJson, LinuxCnc, BeckhoffLsec, Siemens840d, HeidenhainTnc):
        register(cls())
