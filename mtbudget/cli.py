"""The ``mtbudget`` command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from . import __version__
from .errors import MtbudgetError, check_folder, make_folder
from .executors import AUTO_MAX_WORKERS, AUTO_MIN_TRIALS, AUTO_PARALLEL


#: click (>= 8.2) shows a group's help, as a usage error, when it is called without a command: that help stays
_NO_ARGS_IS_HELP = getattr(click.exceptions, "NoArgsIsHelpError", ())


class _Group(click.Group):
    """Turn mtbudget's own errors into one-line messages and exit code 2."""

    ORDER = ("study", "run", "report", "replay", "simulate", "identify", "compensate", "diagnose", "plugins")

    def list_commands(self, ctx):
        names = super().list_commands(ctx)
        return [n for n in self.ORDER if n in names] + [n for n in names if n not in self.ORDER]

    def parse_args(self, ctx, args):
        ctx.meta["mtbudget.argv"] = list(args)  # the command line as given (the first-run note reads it)
        return super().parse_args(ctx, args)

    def invoke(self, ctx):
        # mtbudget's matrices are small: a second BLAS thread only waits on a shared machine (measured 25-60x slower
        # for the placement study and diagnosis on 2 busy cores). Set before numpy loads; the user's setting wins.
        import os

        for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
            os.environ.setdefault(var, "1")
        argv = ctx.meta.get("mtbudget.argv", [])
        _first_run_note(argv)
        from .progress import start_starting, stop_starting

        if argv and argv[0] in _COMPUTING and not {"-h", "--help", "--quiet"} & set(argv):
            start_starting()  # a heartbeat on stderr until the command's first bar or note (not in a CliRunner)
        try:
            return super().invoke(ctx)
        except MtbudgetError as exc:
            stop_starting()
            click.echo(f"error: {exc}", err=True)
            ctx.exit(2)
        except click.UsageError as exc:  # a bad option or argument: one line naming it (click would print three)
            if isinstance(exc, _NO_ARGS_IS_HELP):  # a group called without its command: click shows its help
                raise
            stop_starting()
            where = exc.ctx.command_path if exc.ctx is not None else "mtbudget"
            click.echo(f"error: {exc.format_message()} (see '{where} --help')", err=True)
            ctx.exit(2)
        except KeyboardInterrupt:
            stop_starting()
            click.echo("\ninterrupted (Ctrl-C)", err=True)
            ctx.exit(130)
        finally:
            stop_starting()


def _quiet_option(f):
    """``--quiet`` for a command without a progress option of its own: no bar, note or heartbeat on stderr (its
    results on stdout and its errors still print)."""
    def silence(ctx, param, value):
        from .progress import set_quiet

        set_quiet(value)

    return click.option("--quiet", is_flag=True, expose_value=False, is_eager=True, callback=silence,
                        help="No progress bars, notes or heartbeats on stderr (results and errors still print).")(f)


#: commands that evaluate the kinematic chain (and so call the compiled kernels)
_COMPUTING = {"study", "run", "replay", "simulate", "identify", "compensate", "diagnose"}


def _first_run_note(args: list):
    """Say so on stderr (a terminal, a pipe or a file alike) when the first command after installing compiles the
    engine's kernels (numba, once per machine: 13-34 s measured on 2 busy cores), rather than sit silent; never
    with --quiet or --help (stdout, where --json prints, is never written)."""
    if not args or args[0] not in _COMPUTING or {"-h", "--help", "--quiet"} & set(args):
        return
    from .kernels import compiled_here
    from .kernels_stats import compiled_here as stats_compiled_here

    if compiled_here() is False or stats_compiled_here() is False:
        click.echo("compiling the engine's kernels (numba), once for this machine: 10-40 s ...", err=True)


def _identify_limit() -> int:
    """The most rows a recording may have for a command that identifies it: one identification's limit, checked by
    the reader on the bytes before it parses a row (a 10^6-row file is refused in a second, not after its parse)."""
    from .identify import MAX_POINTS

    return MAX_POINTS


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mtbudget")
def main():
    """Uncertainty budgets for machine-tool volumetric verification with a laser tracker.

    \b
    Start with:
      mtbudget study all --out paper-study   the paper's studies on the built-in default (about 9 CPU s)
      mtbudget run --trials 1000             Monte Carlo uncertainty and budget of the built-in verification
      mtbudget report mtbudget-run.mcap      a Markdown and HTML report of that run
      mtbudget simulate --out sim            one simulated verification written as a recording
      mtbudget identify sim                  identify the machine's errors from a recording
      mtbudget diagnose --example thermal_x  find the physics a recording shows that the model leaves out

    Every command has --help. Quantities in configs and recordings carry units
    (pint syntax: "5 um", "20 degC", "0.8 um/m").
    """


@main.command()
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("mtbudget-simulation"),
              show_default=True, help="Folder to write the simulated recording into (created if missing).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Seed of the run whose trial is written (default: the config's seed).")
@click.option("--trial", type=click.IntRange(min=0), default=0, show_default=True,
              help="Which trial of that run: `mtbudget run` with the same seed simulates the same trial.")
@click.option("--no-identify", is_flag=True, help="Only write the recording; skip the identification summary.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
              help="Change one key of the configuration, e.g. --set 'effects.thermal.x=11.5 um/(m*K)' (repeatable).")
@_quiet_option
def simulate(config, out, seed, trial, no_identify, sets):
    """Simulate a verification and write it as a recording.

    CONFIG is a TOML configuration (default: the built-in paper study,
    examples/paper_xfyz.toml). The recording is one trial of the Monte
    Carlo run of the same configuration: every enabled source (see
    `mtbudget plugins CONFIG`) and the effects of [effects] are drawn by the
    same simulator. The folder gets recording.toml, points.csv and
    truth.json (what the simulation put in), in the format of
    docs/recording-format.md, so a simulation and a real recording can be
    compared point by point.
    """
    from .config import load_config
    from .recording import write_recording
    from .scenario import build_scenario
    from .simulate import simulate_recording

    check_folder(out, "--out")  # before the simulation: a path that cannot be written is said at once
    cfg = load_config(config, sets)
    rec, truth = simulate_recording(build_scenario(cfg), seed, trial)
    write_recording(rec, out, truth=truth)
    click.echo(f"wrote {len(rec)} simulated points of {cfg.name!r} ({cfg.machine}) to {out}/")
    silent = [s.sensor.column for s in cfg.sensors if not s.noise_stated]
    if silent:  # the stated default, said where it takes effect
        click.echo(f"note: no reading noise stated for sensor{'s' if len(silent) > 1 else ''} {', '.join(silent)}: "
                   "simulated noise-free (noise = \"0 K\"); state [[sensors]] noise to simulate it", err=True)
    if not no_identify:
        _print_identification(out)


def _print_identification(folder, as_json=False, max_degree=3, strategy="one-phase", rotary_harmonics=0):
    from .identify import Noise, Strategy, identify, implausible
    from .model import MeasurementModel, iso_parameter
    from .recording import read_recording
    from .units import display, pretty as pretty_unit, shown_unit

    rec = read_recording(folder, several_stations=True, max_rows=_identify_limit())
    if rec.several_stations:  # all stations at once (docs/recording-format.md, format 2)
        from .multistation import identify_recording_any, summary as station_summary, summary_text

        rec, res = identify_recording_any(rec, max_degree=max_degree, strategy=(
            Strategy.one_phase() if strategy == "one-phase" else Strategy.multi_phase()))
        s = station_summary(rec, res)
        s["thermal_correction"] = rec.thermal_correction
        problems = implausible(res)
        if problems:  # as for one tracker, below
            s["warning"] = (f"warning: {rec.path or rec.name}: {problems[0]}"
                            + (f"; also {'; '.join(problems[1:3])}" if len(problems) > 1 else "")
                            + ": this is not an identification of the machine; check the recording's units (the "
                            "column headers of points.csv), its stated noise and the machine code before using any "
                            "number below")
            s["implausible"] = problems
            click.echo(s["warning"], err=True)
        click.echo(json.dumps(s, indent=1) if as_json else "\n".join(summary_text(rec, res) +
                                                                      [f"  {rec.thermal_correction}"]))
        return s
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree,
                                      **({"harmonics": rotary_harmonics} if rec.plan.angles else {}))
    strat = Strategy.one_phase() if strategy == "one-phase" else Strategy.multi_phase()
    res = identify(model, rec.lt, Noise.of(rec), strat, fixed=rec.fixed_inputs())
    u = res.u_theta()[0]
    held = set(res.identifiability.held or [])
    summary = {
        "recording": rec.name,
        "machine": model.config.code,
        "points": len(rec),
        "chi2_per_dof": float(res.chi2_per_dof[0]),
        "dof": int(res.dof),
        "mean_error_before_um": float(display(res.mean_error_before[0], "mm", "um")),
        "mean_error_after_um": float(display(res.mean_error_after[0], "mm", "um")),
        "max_residual_um": float(display(res.max_residual[0], "mm", "um")),
        "converged": bool(res.converged[0]),
        "thermal_correction": rec.thermal_correction,
        "pose": dict(zip("DLHabd", map(float, res.pose[0]))),
        "pose_units": dict(zip("DLHabd", ["mm"] * 3 + ["rad"] * 3)),
        "parameters": [
            {"name": p.name, "iso": iso_parameter(p.name), "value": float(display(v, p.unit, shown_unit(p.unit))),
             "uncertainty": float(display(s, p.unit, shown_unit(p.unit))), "unit": shown_unit(p.unit),
             **({"datum": True} if j in held else {})}
            for j, (p, v, s) in enumerate(zip(model.errors.params, res.theta[0], u))
        ],
        "not_identifiable": [[{"parameter": n, "iso": iso_parameter(n), "weight": w} for n, w in combo]
                             for combo in res.identifiability.combinations()],
    }
    if model.rotary:  # five-axis: the rotary geometry read, and the datum applied (docs/model.md)
        summary["rotary"] = {r.letter.upper(): {"pivot_mm": list(map(float, r.pivot)),
                                                "direction": f"{'+' if r.sign > 0 else '-'}{'xyz'[r.index]}"}
                             for r in model.config.rotary}
        summary["tracker_mount"] = rec.mount
        summary["datum"] = {
            "held": [iso_parameter(model.errors.names[j]) for j in res.identifiability.held or []],
            "rule": "held at 0, one per direction the plan cannot identify: the zero error of the rotary axis that "
                    "carries the workpiece (the table's angular zero is the tracker's); a rotary axis' tilt about "
                    "the direction of the rotary axis carrying it (reported as the carrier's zero error); the "
                    "rotary axes' location offsets, nearest the bed first; the tool offsets are exact",
            "weights_unit": "um or urad of each parameter per um or urad of the held one",
        }
    problems = implausible(res)
    if problems:  # said before any number, on stderr, on stdout and in the JSON (the bounds: mtbudget.identify)
        warn = (f"warning: {rec.path or rec.name}: {problems[0]}"
                + (f"; also {'; '.join(problems[1:3])}" if len(problems) > 1 else "")
                + f" (largest residual {summary['max_residual_um'] / 1000:.3g} mm): this is not an identification of "
                "the machine; check the recording's units (the column headers of points.csv), its stated noise, the "
                "machine code and the rotary axes' pivots and directions before using any number below")
        summary["warning"] = warn
        summary["implausible"] = problems
        click.echo(warn, err=True)
    if as_json:
        click.echo(json.dumps(summary, indent=1))
        return summary
    click.echo(f"identified {rec.name!r}: {len(rec)} points, {res.dof} degrees of freedom")
    if problems:
        click.echo(f"  NOT AN IDENTIFICATION of the machine: {problems[0]}; the numbers below describe that mistake, "
                   "not the machine (the warning on stderr says what to check)")
    click.echo(f"  chi-square per dof        {summary['chi2_per_dof']:.3f}  (1 = residuals match the stated uncertainties)")
    click.echo(f"  mean volumetric error     {summary['mean_error_before_um']:.2f} µm before, "
               f"{summary['mean_error_after_um']:.2f} µm after compensation (paper Eq. 27, fit residuals)")
    click.echo(f"  maximum residual          {summary['max_residual_um']:.2f} µm")
    click.echo(f"  {rec.thermal_correction}")
    if summary["not_identifiable"] and held:
        click.echo("  not identifiable from this plan: each line is a combination the data cannot see; its first "
                   "parameter is held at 0 (the datum, docs/model.md) and each other one is identified as its own "
                   "value minus its weight times the held one's (weights in um or urad per um or urad; ISO "
                   "230-1/230-7 names, mtbudget's in brackets):")
        for combo in res.identifiability.combinations():
            click.echo("    " + " ".join(f"{w:+.3g}*{iso_parameter(n)} ({n})" for n, w in combo))
    elif summary["not_identifiable"]:
        click.echo("  not identifiable from this plan (held at their initial value; ISO 230-1 names, mtbudget's in brackets):")
        for combo in res.identifiability.combinations():
            click.echo("    " + " ".join(f"{w:+.2f}*{iso_parameter(n)} ({n})" for n, w in combo))
    if summary["not_identifiable"] and (folder / "truth.json").is_file():  # a simulation: its truth is not in the datum
        click.echo("  truth.json (a simulation) states the drawn values, not these: a parameter in a combination above "
                   "is identified relative to the datum (its own value minus its weight times the held one's), so "
                   "compare the compensated machine, which does not depend on the datum: "
                   f"`mtbudget compensate {folder} --format neutral-json --out tables.json --check`")
    if model.rotary:
        rows = [(iso_parameter(p.name), float(display(v, p.unit, shown_unit(p.unit))),
                 float(display(s_, p.unit, shown_unit(p.unit))), shown_unit(p.unit), j in held)
                for j, (p, v, s_) in enumerate(zip(model.errors.params, res.theta[0], u)) if p.name.endswith("[O]")]
        click.echo("  rotary axes' location and zero errors (ISO 230-7; u is the standard uncertainty, k = 1):")
        for name, v, s_, unit, h in rows:
            click.echo(f"    {name:<6} {v:+10.2f} {pretty_unit(unit):<5}" + ("  held at 0 (datum)" if h else
                                                                           f"  u = {s_:.2g} {pretty_unit(unit)}"))
    return summary


@main.command()
@click.argument("recording", required=False, type=click.Path(file_okay=False, path_type=Path))
@click.option("--example", type=click.Choice(["null", "thermal_x", "reversal_y", "tracker_drift", "four_stations"]),
              help="Use a bundled example recording instead of a folder.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (parameters with units and uncertainties).")
@click.option("--max-degree", type=click.IntRange(min=1, max=9), default=3, show_default=True,
              help="Legendre degree of each error function.")
@click.option("--strategy", type=click.Choice(["one-phase", "multi-phase"]), default="one-phase", show_default=True,
              help="Optimisation strategy: all errors at once (the paper's choice) or pose, then translational, then all.")
@click.option("--rotary-harmonics", type=click.IntRange(min=0, max=6), default=0, show_default=True,
              help="Five-axis recordings: Fourier terms of each rotary axis' commanded angle in its error motions "
                   "(ISO 230-1 EXC ... ECC); 0 identifies the location and zero errors only (ISO 230-7).")
@_quiet_option
def identify(recording, example, as_json, max_degree, strategy, rotary_harmonics):
    """Identify the tracker pose and geometric errors of a recording.

    RECORDING is a folder with recording.toml and points.csv. Prints the
    chi-square per degree of freedom, the paper's mean volumetric error
    (Eq. 27) before and after compensation, and which error combinations the
    plan cannot identify. A five-axis recording (format 3: rotary axes A, B,
    C) also gives each rotary axis' location and zero errors (ISO 230-7
    names: EXOC, EAOA ...) and the datum the plan needs (docs/model.md).
    """
    from .config import example_recording

    if recording is None and example is None:
        raise click.UsageError("give a RECORDING folder or --example NAME")
    folder = example_recording(example) if example else recording
    _print_identification(folder, as_json, max_degree, strategy, rotary_harmonics)


@main.command("posterior")
@click.argument("recording", required=False, type=click.Path(file_okay=False, path_type=Path))
@click.option("--example", type=click.Choice(["null", "thermal_x", "reversal_y", "tracker_drift"]),
              help="Use a bundled example recording instead of a folder.")
@click.option("--trials", type=click.IntRange(min=2), default=2000, show_default=True,
              help="Monte Carlo trials around the identified errors.")
@click.option("--seed", type=click.IntRange(min=0), default=1, show_default=True)
@click.option("--coverage", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.95, show_default=True)
@click.option("--noise", type=click.Choice(["stated", "estimated"]), default="stated", show_default=True,
              help="The recording's stated noise, or scaled by sqrt(chi2/dof) of the fit (the noise it estimated).")
@click.option("--max-degree", type=click.IntRange(min=1, max=9), default=3, show_default=True)
@click.option("--tolerance", default=None,
              help='Tolerance on the compensated machine\'s error, e.g. "20 um": adds the ISO 14253-1 decision (the '
                   'rule `mtbudget report` applies, on this statement\'s own intervals and trials).')
@click.option("--characteristic", type=click.Choice(["component", "max"]), default="component", show_default=True,
              help="What the tolerance applies to: each error component at each point (component), or the largest "
                   "3-D error over the mesh (max).")
@click.option("--json", "as_json", is_flag=True, help="Print the statement as one JSON object.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write posterior.md, a self-contained posterior.html, posterior.json and certificate.xml (the "
                   "DCC: PTB DCC 3.3.0 XML) into this folder.")
@_quiet_option
def posterior_cmd(recording, example, trials, seed, coverage, noise, max_degree, tolerance, characteristic, as_json,
                  out):
    """The a posteriori statement of a recorded verification.

    The uncertainty of the compensated machine that this verification
    identified: a Monte Carlo around the identified errors with the
    recording's stated noise (or the noise the fit estimated), each trial
    identified as the recording was, with the identification covariance
    propagated linearly beside it as the check. A `run` on a configuration is
    the a priori statement of a planned verification; this is the statement
    of a verification carried out, the one a laboratory signs.

    It opens, as `mtbudget report` does, with the statement in brief: the
    kind of statement (a posteriori: the recording and its points.csv
    sha256), the measurand (five-axis: the workpiece frame, the machine frame
    beside it), the result, U = k u (k = 2 at the default 95 %; the normal
    quantile of --coverage otherwise) with the largest half-width of the
    Monte Carlo intervals, the decision and its rule with --tolerance, the
    chi-square test's warning where the fit fails it, and the laboratory,
    instrument, machine, customer, operator, date and traceability of
    recording.toml's optional [report] table ("not stated" where absent).
    --out writes the same statement as Markdown, HTML, JSON and a DCC.
    """
    from .config import example_recording, to_unit
    from .posterior import posterior_result, posterior_text
    from .report import posterior_json

    if recording is None and example is None:
        raise click.UsageError("give a RECORDING folder or --example NAME")
    tol = None if tolerance is None else to_unit(tolerance, "um", "--tolerance")
    if tol is not None and not tol > 0:
        raise click.BadParameter("must be a positive length, e.g. \"20 um\"", param_hint="--tolerance")
    if out is not None:
        check_folder(out, "--out")
    folder = example_recording(example) if example else recording
    post = posterior_result(folder, trials=trials, seed=seed, coverage=coverage, noise=noise, max_degree=max_degree)
    p = posterior_json(post, tol, characteristic)
    if p["identification"]["fit_test"]["warning"]:  # said on stderr too, where a script that reads --json sees it
        click.echo(f"warning: {p['identification']['fit_test']['warning']}", err=True)
    click.echo(json.dumps(p, indent=1) if as_json else posterior_text(p))
    if out is not None:
        from .report import posterior_report
        from .report_dcc import write_dcc

        from .report import no_certificate_line, too_many_not_converged

        make_folder(out, "--out")  # a folder that cannot be made (as root, /proc passes the early check) names --out
        paths = posterior_report(post, out, tol, characteristic)
        _remove_stale_certificate(out)  # written again below if this statement gives one
        if too_many_not_converged(p.get("not_converged", 0), p["trials"]):  # as a run's: no certificate
            said = "; " + no_certificate_line(p["not_converged"], p["trials"])
            click.echo(f"warning: {said[2:]}", err=True)
        elif (p.get("report") or {}).get("date"):
            dcc = write_dcc(post, Path(out) / "certificate.xml", tol, characteristic)
            said = f" and {dcc} (the DCC: PTB DCC 3.3.0 XML)"
        else:  # a certificate's performance date is the measurement's: never the day of this evaluation
            said = ("; certificate.xml is not written: recording.toml states no [report] date, the date of the "
                    "measurement, which a certificate gives as its performance date")
            click.echo(f"note: {said[2:]}", err=True)
        if not as_json:  # stdout stays one JSON object
            click.echo(f"wrote {paths['markdown']}, {paths['html']}, {paths['json']}{said}")


def _remove_stale_certificate(out) -> None:
    """A certificate.xml left in an output folder by an earlier statement must not stand for this one: removed
    before a statement that writes none (``report`` of a run that did not converge, ``posterior`` without a [report]
    date or with too many trials not converged)."""
    stale = Path(out) / "certificate.xml"
    if stale.exists():
        stale.unlink()


@main.command("compensate")
@click.argument("recording", required=False, type=click.Path(file_okay=False, path_type=Path))
@click.option("--example", type=click.Choice(["null", "thermal_x", "reversal_y", "tracker_drift"]),
              help="Use a bundled example recording instead of a folder.")
@click.option("--format", "fmt", required=True,
              help="Exporter: neutral-csv, neutral-json, linuxcnc, beckhoff-lsec, siemens-840d, heidenhain-tnc, or one a "
                   "plugin registers (`mtbudget plugins` lists them; docs/compensation.md gives each convention).")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="File to write (its folder is created); a format of several files writes FILE_x, FILE_y, FILE_z "
                   "(LinuxCNC, Beckhoff), FILE_eec and FILE_cec (Siemens) or one .COM per axis and a .CMA (Heidenhain), "
                   "with the same suffix.")
@click.option("--step", default="50 mm", show_default=True, help="Grid step of the tables along every axis.")
@click.option("--check", is_flag=True,
              help="Read the written tables back and apply them to the simulated machine of the recording's truth.json; "
                   "ends with a verdict per axis and cross table: improved, worse or under-covered.")
@click.option("--strict", is_flag=True, help="With --check: exit with code 1 when an axis or cross table gets worse.")
@click.option("--reference", "reference", multiple=True, metavar="AXIS=LENGTH",
              help="Reference point of an axis, where its tables are zero (repeatable, e.g. --reference \"x=500 mm\"); "
                   "default 0 mm, the machine zero, for every axis.")
@click.option("--siemens-cec-sign", type=click.Choice(["error", "correction"]), default=None,
              help="Required with siemens-840d / siemens-828d: what a $AN_CEC entry is, the measured error (a positive "
                   "value moves the axis in -, as LEC) or the correction added to the setpoint; no Siemens text found "
                   "states it: docs/compensation.md gives a one-value test on the machine.")
@click.option("--max-degree", type=click.IntRange(min=1, max=9), default=3, show_default=True,
              help="Legendre degree of each error function.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (the table, ISO 230-2 figures, the check).")
@click.option("--report", "report_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write compensation.md and a self-contained compensation.html into this folder: the tables, "
                   "ISO 230-2 figures, the fit residual against U (k = 2) with its figure, and the check.")
@_quiet_option
def compensate(recording, example, fmt, out, step, check, strict, reference, siemens_cec_sign, max_degree, as_json,
               report_dir):
    """Identify a recording and write its compensation tables for a controller.

    RECORDING is a folder with recording.toml and points.csv. The geometric
    errors are identified as by `mtbudget identify`, sampled every --step
    over the measured range under their ISO 230-1 names with the standard
    uncertainty of each entry, and written with the exporter --format. Also
    printed: ISO 230-2 figures (A, E, M, R, B) per axis from the recording's
    bidirectional approaches and from the identified model. With --check
    (a recording from `mtbudget simulate`), the written files are read back
    and applied to the simulated machine: the positioning error left after
    compensation against the uncertainty the table states. Conventions and
    sources of each format: docs/compensation.md.
    """
    from .compensate import (build_table, check_export, check_json, check_worse, export, find_exporter,
                             parse_reference, parse_step, table_text)
    from .progress import note
    from .config import example_recording
    from .recording import read_recording

    if recording is None and example is None:
        raise click.UsageError("give a RECORDING folder or --example NAME")
    check_folder(Path(out).parent, "--out")
    if report_dir is not None:
        check_folder(report_dir, "--report")
    step_mm = parse_step(step)
    ref_point = parse_reference(reference)
    exporter = find_exporter(fmt)
    rec = read_recording(example_recording(example) if example else recording, max_rows=_identify_limit())
    table = build_table(rec, step_mm, max_degree=max_degree, reference_point=ref_point)
    table.options["siemens_cec_sign"] = siemens_cec_sign
    written = export(table, exporter, out)
    result = check_export(table, rec, exporter, written) if check else None
    if report_dir is not None:
        from .report import compensation_report

        paths = compensation_report(table, report_dir, check_json(result) if result is not None else None)
        note(f"report: {paths['markdown']} and {paths['html']}", not as_json)
    if as_json:
        body = {**table.to_dict(), "written": [str(p) for p in written], "format_name": exporter.name}
        if result is not None:
            body["check"] = check_json(result)
        click.echo(json.dumps(body, indent=1))
    else:
        click.echo(table_text(table, written, exporter, result))
    if strict and result is not None and check_worse(result):
        click.get_current_context().exit(1)  # a failed verdict, not bad input (2)


@main.command("plugins")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the table.")
def plugins_cmd(config, as_json):
    """List every plugin, uncertainty source, diagnosis candidate and exporter.

    For each source: its group (the paper's four), distribution, parameters
    with units, whether it is opt-in (off unless a configuration enables
    it), and the plugin, distribution and version it came from. With CONFIG,
    each source is marked "on" or "off" for that configuration, with the
    parameter values the run will draw. MTBUDGET_DISABLE_PLUGINS=a,b and
    MTBUDGET_PLUGINS=a,b (allow-list) select which plugins load;
    MTBUDGET_TRACE_PLUGINS=1 traces every hook call on stderr.
    """
    from .plugins import PluginHost

    host = PluginHost()
    sources = host.sources()
    enabled = None
    if config is not None:
        from .config import load_config
        from .scenario import build_scenario

        enabled = {s.name: s for s in build_scenario(load_config(config), host).sources}

    def params(src):
        from .units import pretty

        return {k: ({"value": float(v.magnitude), "unit": pretty(str(v.units))} if hasattr(v, "units") else str(v))
                for k, v in src.parameters.items()}

    data = {
        "plugins": [vars(p) for p in host.plugins()],
        "sources": [{"name": s.name, "group": str(s.group.value if hasattr(s.group, "value") else s.group),
                     "distribution": s.distribution, "plugin": s.plugin, "package": s.dist_name, "version": s.dist_version,
                     "opt_in": bool(s.opt_in), "targets": list(s.targets),
                     "parameters": params(enabled[s.name] if enabled and s.name in enabled else s),
                     **({} if enabled is None else {"enabled": s.name in enabled}),
                     "description": (type(s).__doc__ or "").strip().splitlines()[0] if type(s).__doc__ else ""}
                    for s in sources],
        "candidates": [{"effect": c.effect, "axis": c.axis, "plugin": c.plugin, "package": c.dist_name}
                       for c in host.candidates()],
        "exporters": [{"name": e.name, "description": e.description, "suffix": e.suffix, "plugin": e.plugin,
                       "package": e.dist_name} for e in host.exporters()],
        "skipped": [str(x) for x in getattr(host, "skipped", [])],
    }
    if as_json:
        click.echo(json.dumps(data, indent=1))
        return
    click.echo("plugins:")
    for p in data["plugins"]:
        click.echo(f"  {p['name']:<24} {p['module']:<40} {p['distribution']} {p['version']}")
    for p in data["skipped"]:
        click.echo(f"  skipped: {p}")
    click.echo("\nuncertainty sources" + (f" (on / off for {config})" if config is not None else "") + ":")
    for s in data["sources"]:
        ps = ", ".join(f"{k}={v['value']:g} {v['unit']}".rstrip() if isinstance(v, dict) else f"{k}={v}"
                       for k, v in s["parameters"].items()) or "-"
        state = "" if enabled is None else ("on   " if s["enabled"] else "off  ")
        opt = " (opt-in)" if s["opt_in"] else ""
        click.echo(f"  {state}{s['name']:<32} [{s['group']}] {s['distribution']}{opt}")
        click.echo(f"      {ps}   (plugin {s['plugin']}, {s['package']} {s['version']})")
    if data["candidates"]:
        click.echo("\ndiagnosis candidates:")
        for c in data["candidates"]:
            click.echo(f"  {c['effect']:<24} axis {c['axis'] or '-':<4} (plugin {c['plugin']})")
    if data["exporters"]:
        click.echo("\ncompensation exporters (mtbudget compensate --format NAME):")
        for e in data["exporters"]:
            click.echo(f"  {e['name']:<16} {e['description']} (plugin {e['plugin']})")


@main.command("run")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--trials", type=click.IntRange(min=0), default=1000, show_default=True,
              help="Monte Carlo trials (at least 2); 0 runs the adaptive procedure of JCGM 101 7.9 on every point-axis of the "
                   "measurand (u and interval ends) and the main output "
                   "(two significant digits: expect hundreds of thousands of trials; at most --max-trials, 10^6 by "
                   "default).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Seed of the run (default: the config's seed).")
@click.option("--coverage", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.95, show_default=True,
              help="Coverage probability of the intervals.")
@click.option("--executor", type=click.Choice(["auto", "inline", "thread", "process", "dask"]), default="auto", show_default=True,
              help=f"Where trials run: auto (inline below {AUTO_MIN_TRIALS:,} trials of work, the budget's included; "
                   f"above, {AUTO_PARALLEL} workers on the machine's cores, at most {AUTO_MAX_WORKERS}), inline (this "
                   "process, one core: best when the cores are busy with other work), threads of this process, a "
                   "local process pool, or a Dask cluster (extra 'dask'); the numbers are the same whichever "
                   "(docs/performance.md, \"Executors on two cores\").")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help=f"Worker threads (default: this machine's cores; with auto at most {AUTO_MAX_WORKERS}), worker "
                   "processes (default 2) or local Dask workers (default 2); refused with --executor inline and with "
                   "--address. The output says which executor ran, with its workers.")
@click.option("--address", default=None,
              help="Address of an existing Dask scheduler, e.g. tcp://host:8786 (worked example: docs/performance.md); "
                   "needs --executor dask; results are bit-identical to an inline run.")
@click.option("--attribution-trials", type=click.IntRange(min=0), default=512, show_default=True,
              help="Trials per source for the budget (one source at a time); 0 skips the budget.")
@click.option("--log", "log_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the run to this MCAP file (default: mtbudget-run.mcap; an existing file needs --force).")
@click.option("--force", is_flag=True, help="Overwrite an existing run log or an interrupted one (LOG.partial); "
                                            "never one that another run is writing.")
@click.option("--resume", "resume_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Finish an interrupted run from its MCAP log (LOG or LOG.partial; same config and seed): the "
                   "verified blocks are kept, damaged or missing ones recomputed.")
@click.option("--block", type=click.IntRange(min=1, max=100_000), default=64, show_default=True,
              help="Trials per block: the unit the run log saves and --resume reuses. Each block draws from its "
                   "own random stream, so a seed repeats the same trials only with the same block size "
                   "(a resume takes it from the log).")
@click.option("--adaptive-batch", type=click.IntRange(min=2), default=None,
              help="With --trials 0: trials per adaptive batch (default: JCGM 101's max(100/(1-p), 10^4)).")
@click.option("--max-trials", type=click.IntRange(min=2), default=None,
              help="With --trials 0: the trial limit of the adaptive run (default 10^6): it stops at the end of the "
                   "batch that reaches it, so at most one batch past it; at least two batches. A run that reaches it "
                   "says how many quantities were not stable, the worst with their tolerance, and about how many "
                   "trials they need. Memory stays bounded whatever the limit.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as one JSON object (progress still goes to stderr).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
              help="Change one key of the configuration, e.g. --set 'sources.tracker_noise.angular_sd=3 urad' "
                   "(repeatable; docs/configuration.md, \"Overlays\").")
def run_cmd(config, trials, seed, coverage, executor, workers, address, attribution_trials, log_path, force, resume_path,
            block, adaptive_batch, max_trials, as_json, quiet, sets):
    """Monte Carlo uncertainty of a planned verification (a priori, a virtual experiment), with its budget.

    CONFIG is a TOML configuration (default: the built-in paper study; a
    five-axis machine: examples/five_axis_cafxyz.toml, rotary axes in
    [rotary.<A|B|C>], docs/user-guide.md "Five-axis machines"). Each
    trial draws every enabled uncertainty source (see `mtbudget plugins
    CONFIG`), simulates the verification, identifies the machine as the real
    verification would, and records the error left after compensation. The
    output gives, for each result, the MCM estimate, standard uncertainty
    and coverage intervals, and a budget by source and by group. Progress
    goes to stderr; the run is logged to MCAP as it goes (see `mtbudget
    replay` and `mtbudget report`): into LOG.partial, renamed to LOG when
    the run completes. A killed run is finished with --resume LOG; a second
    run on the same log is refused. If the log cannot be written (a full
    disk), the results are still printed, a warning says what happened and
    the exit status is 1; LOG.partial keeps what was written (docs/runlog.md).
    """
    from .report import budget_text, result_json
    from .runner import RunSettings, execute

    if trials == 1:
        raise click.BadParameter("a Monte Carlo run needs at least 2 trials (or 0 for an adaptive run)",
                                 param_hint="--trials")
    if attribution_trials == 1:
        raise click.BadParameter("the budget needs at least 2 trials per source (or 0 to skip it)",
                                 param_hint="--attribution-trials")
    _refuse_contradictions(trials, executor, workers, address, adaptive_batch, max_trials, resume_path)
    if log_path is not None:
        check_folder(Path(log_path).parent, "--log")
    settings = RunSettings(trials=trials or None, seed=seed, coverage=coverage, executor=executor, workers=workers,
                           address=address, attribution_trials=attribution_trials, progress=not quiet,
                           adaptive_batch=adaptive_batch, block=block,
                           **({} if max_trials is None else {"max_trials": max_trials}))
    if sets:
        if resume_path is not None:
            raise click.UsageError("--set changes a configuration; a resume continues the logged one")
        from .config import load_config

        config = load_config(config, sets)
    import signal
    import threading

    terminated = []  # SIGTERM (timeout, a batch scheduler, kill): stopped as Ctrl-C stops it, and said so

    def on_term(signum, frame):
        terminated.append(signum)
        raise KeyboardInterrupt

    before = (signal.signal(signal.SIGTERM, on_term) if threading.current_thread() is threading.main_thread()
              else None)
    try:
        res = execute(config, settings, log_path=log_path, resume_path=resume_path, force=force)
    except KeyboardInterrupt:
        from .runner import DEFAULT_LOG
        from .runlog import final_path, partial_path

        how = "terminated (SIGTERM)" if terminated else "interrupted"
        target = final_path(log_path or resume_path or DEFAULT_LOG)
        if partial_path(target).exists():
            click.echo(f"\n{how}: the blocks of trials finished so far are saved in {partial_path(target)}; "
                       f"finish the run with `mtbudget run --resume {target}` (the same numbers as an uninterrupted "
                       "run)", err=True)
        else:
            click.echo(f"\n{how} before the first block of trials was saved; nothing to resume", err=True)
        raise SystemExit(143 if terminated else 130) from None
    finally:
        if before is not None:
            signal.signal(signal.SIGTERM, before)
    if as_json:
        click.echo(json.dumps(result_json(res), indent=1))
    else:
        click.echo(budget_text(res))
    if res.not_converged:  # on stderr too, where a script that reads --json (or a log of stdout alone) sees it
        from .report import not_converged_line

        click.echo(f"warning: {not_converged_line(res.not_converged, res.trials)[len('WARNING: '):]}", err=True)
    for n in res.resume_notes:
        click.echo(f"note: resume: {n}", err=True)
    if resume_path is not None:  # an option given with --resume that the logged run overrides: said, not ignored
        ctx = click.get_current_context()
        given = {k for k in ("trials", "seed", "coverage", "block", "attribution_trials", "adaptive_batch", "max_trials")
                 if ctx.get_parameter_source(k) == click.core.ParameterSource.COMMANDLINE}
        kept = {k: v for k, v in getattr(res, "resume_kept", {}).items() if k in given}
        if config is not None:
            click.echo(f"note: resume: the run keeps its logged configuration ({config} was not used)", err=True)
        if kept:
            click.echo("note: resume: the run keeps its logged settings: " + ", ".join(
                f"--{k.replace('_', '-')} {v}" for k, v in kept.items()) + " (the options given were not used)", err=True)
    if res.log_problem:
        click.echo(f"warning: {res.log_problem}", err=True)
        raise SystemExit(1)


def _refuse_contradictions(trials, executor, workers, address, adaptive_batch, max_trials, resume_path):
    """Options of ``run`` that cannot apply together: refused in one line, never silently ignored."""
    if workers is not None and executor == "inline":
        raise click.UsageError("--workers sets parallel workers; --executor inline runs the trials in this process on "
                               "one core (leave out --workers, or choose --executor thread, process, dask or auto)")
    if address is not None and executor != "dask":
        raise click.UsageError(f"--address names a Dask scheduler; it needs --executor dask (given: {executor})")
    if address is not None and workers is not None:
        raise click.UsageError("--workers starts local Dask workers; with --address the scheduler's own workers run "
                               "the trials (leave out --workers)")
    for name, value in (("--adaptive-batch", adaptive_batch), ("--max-trials", max_trials)):
        if value is not None and trials != 0 and resume_path is None:  # a resume: the logged run's (noted after it)
            raise click.UsageError(f"{name} applies to an adaptive run (--trials 0); --trials {trials} runs exactly "
                                   "that many trials")


@main.command()
@click.argument("runlog", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--verify", is_flag=True, help="Re-run from the logged config and seed and compare bit for bit.")
@click.option("--json", "as_json", is_flag=True, help="Print the rebuilt results as one JSON object.")
@_quiet_option
def replay(runlog, verify, as_json):
    """Rebuild a logged run's budget and intervals from its MCAP file.

    Nothing is recomputed: the per-trial results in the log are merged again
    in the same order. A run that was cut short is read up to its last
    complete block and marked INCOMPLETE (finish it with `mtbudget run
    --resume`). With --verify the trials are recomputed from the logged
    configuration and seed and compared bit for bit; plugin versions that
    differ from the logged ones are named first; an incomplete log fails the
    verification. A placement study log (study placement) prints its summary.
    """
    from .report import budget_text, result_json
    from .runlog import log_kind, read_placement_log
    from .runner import replay as do_replay
    from .runner import verify as do_verify

    if verify and as_json:  # the check prints its own lines: --json would be ignored
        raise click.UsageError("--json prints the rebuilt results; --verify prints the bit-for-bit check (use one)")
    if log_kind(runlog) == "placement":
        if verify:
            raise click.UsageError("--verify recomputes Monte Carlo runs; a placement study log has none")
        body = read_placement_log(runlog)
        body.pop("arrays", None)
        if as_json:
            click.echo(json.dumps(body, indent=1))
            return
        red = body["reduction"]
        click.echo(f"placement study: {body['settings']['tests']} tests per direction, {body['settings']['candidates']} "
                   "candidate stations per test")
        for k, d in body["directions"].items():
            e = d["max_error_um"]
            click.echo(f"  {k} direction: maximum u_p over the mesh at the best station, mean {e['mean']:.1f} µm, "
                       f"std {e['std']:.1f} µm, 5-95 % [{e['p05']:.1f}, {e['p95']:.1f}] µm")
        click.echo(f"  {red['better']} is better by {red['reduction']:.0%}")
        return
    if verify:
        v = do_verify(runlog, progress=True)
        for n in v["notes"]:
            click.echo(f"note: {n}")
        if v["identical"]:
            click.echo(f"verified: {v['trials']} trials in {v['blocks']} blocks recomputed, bit for bit identical")
        elif not v["complete"] and len(v["mismatches"]) == 1:  # nothing differs: the log is not a whole run
            click.echo(f"NOT verified as a whole run: its {v['trials']} trials in {v['blocks']} blocks recomputed, bit "
                       f"for bit identical, but {v['mismatches'][0]}")
            raise SystemExit(1)
        else:
            click.echo(f"NOT identical: {len(v['mismatches'])} differences")
            for m in v["mismatches"][:20]:
                click.echo(f"  {m}")
            raise SystemExit(1)
        return
    res = do_replay(runlog)
    if as_json:
        click.echo(json.dumps({**result_json(res), **({"exact_from_log": res.exact_from_log}
                                                       if res.exact_from_log else {})}, indent=1))
        return
    if not res.complete:
        logged = sum(int(b.get("n", 0)) for b in getattr(res.log, "blocks", []) or [])
        upto = (f" up to its last histogram checkpoint ({logged} trials logged; a resume restores the checkpoint and "
                "recomputes the blocks after it)" if logged > res.trials else " it holds")
        click.echo(f"INCOMPLETE run log ({res.log.problem}); results from the {res.trials} trials{upto}:")
    click.echo(budget_text(res))
    x = res.exact_from_log
    if x:  # the run's intervals above, by its method; the log holds every value, so the exact ones beside
        from .stats import decimals_for, percent
        from .units import pretty

        un, nd = pretty(x["unit"]), decimals_for(res.summary(x["output"])["std"]) + 1
        click.echo(f"beside the run's histogram intervals: {x['output']} from the order statistics of the {x['n']} "
                   f"logged trials (JCGM 101 7.7), {percent(x['coverage'])} coverage: symmetric "
                   f"[{x['symmetric'][0]:.{nd}f}, {x['symmetric'][1]:.{nd}f}] {un}, shortest "
                   f"[{x['shortest'][0]:.{nd}f}, {x['shortest'][1]:.{nd}f}] {un}")


@main.command("diagnose")
@click.argument("recording", required=False, type=click.Path(file_okay=False, path_type=Path))
@click.option("--example", type=click.Choice(["null", "thermal_x", "reversal_y", "tracker_drift", "four_stations"]),
              help="Diagnose a bundled example recording.")
@click.option("--json", "as_json", is_flag=True, help="Print exactly one JSON object on stdout.")
@click.option("--report", "report_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write a Markdown and a self-contained HTML report (diagnosis.md, diagnosis.html) with residual "
                   "plots before and after into this folder.")
@click.option("--alpha", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.01, show_default=True,
              help="Family-wise false-discovery level over all candidates (Bonferroni).")
@click.option("--max-degree", type=click.IntRange(min=1, max=9), default=3, show_default=True,
              help="Legendre degree of the baseline error functions.")
@click.option("--quiet", is_flag=True, help="No progress bar on stderr.")
def diagnose_cmd(recording, example, as_json, report_dir, alpha, max_degree, quiet):
    """Find the physics a recording shows that the rigid-body model leaves out.

    The recording is identified like a simulated verification (weighted by
    its stated uncertainties); the residuals are located by run, time,
    approach direction, axis position and temperature; every candidate
    physics term (thermal expansion, reversal, tracker drift, ... see
    `mtbudget plugins`) is tested, sets of them are compared, and the effects
    that hold up are named with their estimate, uncertainty and the fit
    before and after. Candidates the data cannot tell apart are reported as
    confounded. A recording that stays unexplained gets no finding: what is
    left is located and described (data-driven, not a named physical effect),
    and candidates that would explain only part of it are listed as partial.
    The noise is estimated beside the stated one. The scales' expansion is
    corrected to the reference temperature where recording.toml states it
    ([scales], docs/recording-format.md).
    """
    from .config import example_recording
    from .diagnose import diagnose
    from .recording import read_recording

    if recording is None and example is None:
        raise click.UsageError("give a RECORDING folder or --example NAME")
    if report_dir is not None:
        check_folder(report_dir, "--report")
    folder = example_recording(example) if example else recording
    rec = read_recording(folder, several_stations=True,  # several stations: every station identified together
                         max_rows=_identify_limit())
    d = diagnose(rec, alpha=alpha, max_degree=max_degree, progress=not quiet)
    if report_dir is not None:
        from .report_diagnosis import diagnosis_report

        diagnosis_report(d, rec, report_dir)
    if as_json:
        click.echo(json.dumps(d.to_dict()))
        return
    from .report_diagnosis import diagnosis_text

    click.echo(diagnosis_text(d))
    if report_dir is not None:
        click.echo(f"\nreport: {report_dir}/diagnosis.md and diagnosis.html")


@main.command()
@click.argument("runlog", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("mtbudget-report"),
              show_default=True, help="Folder for report.md, report.html (self-contained) and the figures.")
@click.option("--tolerance", default=None,
              help='Tolerance on the compensated machine\'s error, e.g. "20 um": adds the ISO 14253-1 decision.')
@click.option("--characteristic", type=click.Choice(["component", "max"]), default="component", show_default=True,
              help="What the tolerance applies to: each error component at each point (component), or the largest "
                   "3-D error over the mesh (max).")
@_quiet_option
def report(runlog, out, tolerance, characteristic):
    """Write an uncertainty statement (Markdown, HTML and a DCC) from a run log.

    It opens with the statement in brief a laboratory issues: the kind of
    statement (a priori: a planned verification evaluated by simulation), the
    measurand in words, the result, U with its k (2 at the default 95 %; the
    normal quantile of the run's --coverage otherwise) and the coverage, the
    decision and its rule, and the laboratory, instrument (tracker model,
    serial, calibration), machine, customer, operator, date and traceability
    sentence of the configuration's optional [report] table ("not stated"
    where absent). The same statement is written as certificate.xml, a
    Digital Calibration Certificate (PTB DCC 3.3.0, D-SI quantities). Then:
    the measurand (the
    error of the compensated machine at each mesh point, per axis), the
    conditions (configuration, machine, mesh, tracker, sources, seed,
    versions), the result (u per axis over the mesh, the worst point, the
    coverage intervals of every point), the budget by source and by group,
    GUF vs MCM per point (JCGM 101 clause 8), the decision when a tolerance
    is given (the rule stated), the paper's volume summaries, and figures
    (u per point and axis over the mesh, distributions, contributions,
    convergence). The HTML opens in a browser with no network.
    """
    from .config import to_unit
    from .progress import note, working
    from .report import run_report
    from .report_dcc import write_dcc
    from .runner import replay as do_replay

    tol = None if tolerance is None else to_unit(tolerance, "um", "--tolerance")
    if tol is not None and not tol > 0:
        raise click.BadParameter("must be a positive length, e.g. \"20 um\"", param_hint="--tolerance")
    check_folder(out, "--out")
    res = do_replay(runlog)
    note(f"writing the report and its figures into {out}/ ...")
    from .report import no_certificate_line, too_many_not_converged

    refused = too_many_not_converged(res.not_converged, res.trials)
    with working("report and figures"):
        make_folder(out, "--out")
        paths = run_report(res, out, tol, characteristic)
        dcc = None if refused else write_dcc(res, Path(out) / "certificate.xml", tol, characteristic)
    if refused:  # as a posteriori without a date: said, the report written, no certificate
        _remove_stale_certificate(out)
        click.echo(f"warning: {no_certificate_line(res.not_converged, res.trials)}", err=True)
    if tol is not None:  # the decision on the console too, not only below the report's tables
        from .budget import conformance

        click.echo("decision (ISO 14253-1): " + conformance(res, tol, characteristic)["statement"])
    click.echo(f"wrote {paths['markdown']} and {paths['html']}" +
               (f" and {dcc} (the DCC: PTB DCC 3.3.0 XML)" if dcc else "; no certificate.xml (see the warning)")
               + ("" if res.complete else " (INCOMPLETE run)"))


@main.group()
def study():
    """The paper's studies (tracker placement, 1000 simulated verifications) and the studies of several stations.

    \b
      mtbudget study all --out paper-study          both, on the built-in paper configuration
      mtbudget study placement --tests 100000       paper Figs. 9-11
      mtbudget study verification --trials 1000     paper Figs. 12-15 with the full budget
      mtbudget study stations                       one station or four, side by side (not in the paper)
      mtbudget study station-placement              where to put 1-4 stations (not in the paper)
    """


#: what each study writes first into its --out folder: a folder holding one already is not overwritten silently
STUDY_FILES = {"placement": "placement.mcap", "verification": "verification.mcap", "readings": "readings.md",
               "stations": "stations.json", "station-placement": "station_placement.json"}


def _fresh_out(out: Path, studies: tuple, force: bool):
    """Refuse to overwrite a previous study in ``out`` unless --force (as `run` refuses to overwrite a log), and an
    ``out`` that cannot be created, before the study runs."""
    check_folder(out, "--out")
    if force:
        return
    for study in studies:
        if (out / STUDY_FILES[study]).exists():
            from .errors import MtbudgetError

            raise MtbudgetError(f"{out / STUDY_FILES[study]}: a {study} study is already there; choose another --out "
                                "or pass --force to replace it")


def _placement(config, tests, out, quiet):
    from .config import load_config
    from .report_study import placement_report
    from .runlog import write_placement_log
    from .scenario import build_scenario
    from .study import placement, placement_arrays, placement_json

    from .progress import working

    cfg = load_config(config)
    res = placement(build_scenario(cfg), tests=tests, progress=not quiet)
    make_folder(out, "--out")
    with working("writing the placement log, report and figures", not quiet):
        summary = placement_json(res)
        write_placement_log(summary, placement_arrays(res), out / "placement.mcap",
                            cfg.path.read_text() if cfg.path else None, cfg.seed)
        md = placement_report(res, summary, out)
    red = res["reduction"]
    click.echo(f"placement: {res['settings']['tests']} tests per direction in {res['seconds']:.0f} s; mean maximum error "
               f"{red['mean_better_um']:.1f} µm ({red['better']} direction) vs {red['mean_worse_um']:.1f} µm "
               f"({red['worse']}): {red['reduction']:.0%} lower (paper: about 30 %)")
    click.echo(f"  report: {md} and {md.with_suffix('.html')}, log: {out / 'placement.mcap'}")


def _verification(config, trials, out, quiet, attribution_trials):
    from .config import load_config
    from .progress import note
    from .report import budget_text, run_report
    from .report_study import STUDY_CAPTIONS, verification_figures
    from .runner import RunSettings, execute, replay
    from .scenario import build_scenario
    from .study import verification_clouds, verification_summary

    cfg = load_config(config)
    if cfg.stations:  # before the run: the figures that follow it identify one tracker
        from .study import one_tracker

        one_tracker(build_scenario(cfg, sources=[]), "the paper's verification study (Figs. 12-15)")
    make_folder(out, "--out")
    try:
        execute(cfg, RunSettings(trials=trials, progress=not quiet, attribution_trials=attribution_trials),
                log_path=out / "verification.mcap", force=True)
    except KeyboardInterrupt:
        from .runlog import partial_path

        log = out / "verification.mcap"
        where = (f"the blocks finished so far are saved in {partial_path(log)} (`mtbudget run --resume {log}` finishes "
                 "that run)" if partial_path(log).exists() else "no block of trials was saved yet")
        click.echo(f"\ninterrupted: {where}; run the study again with --force for its report and figures", err=True)
        raise SystemExit(130) from None
    res = replay(out / "verification.mcap")
    from .progress import working

    note("writing the report and the figures of paper Figs. 12-15 ...", not quiet)
    with working("report and figures", not quiet):
        init, final = verification_clouds(res, build_scenario(cfg, sources=res.spec["sources"]))
        figs = verification_figures(res, init, final, res.mesh, out / "report")
        run_report(res, out / "report", extra_figures={k: (p, STUDY_CAPTIONS.get(k, k)) for k, p in figs.items()})
    summ = verification_summary(res)
    (out / "verification.json").write_text(json.dumps(summ, indent=1, default=float))
    fm = summ["mean_error_after_um"]
    click.echo(budget_text(res))
    ec = summ["compensation_mean_um"]
    click.echo(f"\npaper Eq. 27 read as the compensated machine's error (compensation_mean, per verification): "
               f"mean {ec['mean']:.2f} µm, sigma {ec['sigma']:.2f} µm, mean + 2 sigma {ec['mean_plus_2sigma']:.2f} µm; "
               f"largest point error (compensation_max) below {ec['max_p95']:.1f} µm in 95 % of the verifications "
               f"(paper: 13.77, 5.02, 23.81 µm, about 50 µm)")
    click.echo(f"  paper Eq. 27 read as the fit residual (mean_error_after): mean {fm['mean']:.2f} µm, sigma "
               f"{fm['sigma']:.2f} µm, 95 % below {fm['p95']:.2f} µm; largest residual (max_residual) "
               f"{summ['max_residual_um']['max']:.1f} µm (every reading: the side-by-side tables of `study all`, "
               "docs/paper-reproduction.md)")
    click.echo(f"  report: {out / 'report' / 'report.html'}; figures: {', '.join(p.name for p in figs.values())}")


@study.command("placement")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--tests", type=click.IntRange(min=1), default=None, help="Monte Carlo tests per direction (default: the config's, 100000).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("paper-study"), show_default=True)
@click.option("--force", is_flag=True, help="Replace a previous study in --out.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def study_placement(config, tests, out, quiet, force):
    """Tracker placement (paper Figs. 9-11): best station and maximum error per test, along X and along Y."""
    _fresh_out(out, ("placement",), force)
    _placement(config, tests, out, quiet)


@study.command("verification")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--trials", type=click.IntRange(min=2), default=1000, show_default=True, help="Simulated verifications.")
@click.option("--attribution-trials", type=click.IntRange(min=0), default=256, show_default=True,
              help="Trials per source for the budget (0 skips it).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("paper-study"), show_default=True)
@click.option("--force", is_flag=True, help="Replace a previous study in --out.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def study_verification(config, trials, attribution_trials, out, quiet, force):
    """1000 verifications from the chosen station (paper Figs. 12-15), with the budget by group."""
    _fresh_out(out, ("verification",), force)
    _verification(config, trials, out, quiet, attribution_trials)


@study.command("all")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--tests", type=click.IntRange(min=1), default=None, help="Placement tests per direction (default: the config's).")
@click.option("--trials", type=click.IntRange(min=2), default=1000, show_default=True, help="Simulated verifications.")
@click.option("--attribution-trials", type=click.IntRange(min=0), default=256, show_default=True,
              help="Trials per source for the budget (0 skips it).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("paper-study"), show_default=True)
@click.option("--force", is_flag=True, help="Replace a previous study in --out.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def study_all(config, tests, trials, attribution_trials, out, quiet, force):
    """Both studies of the paper, on the built-in paper configuration unless CONFIG is given."""
    from .config import load_config

    cfg = load_config(config)
    if cfg.stations:
        from .errors import ConfigError

        raise ConfigError(f"{cfg.where('stations')}: the paper's studies: the paper's one tracker only; for "
                          "[[stations]] use `mtbudget study stations` and `mtbudget study station-placement`")
    _fresh_out(out, ("placement", "verification", "readings"), force)
    _placement(config, tests, out, quiet)
    _verification(config, trials, out, quiet, attribution_trials)
    _readings(config, out, quiet, trials)


@study.command("stations")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--trials", type=click.IntRange(min=2), default=256, show_default=True,
              help="Simulated verifications per variant (one station; all stations).")
@click.option("--attribution-trials", type=click.IntRange(min=0), default=64, show_default=True,
              help="Trials per source for each variant's budget (0 skips it).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Seed of both runs (default: the config's seed).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("stations-study"),
              show_default=True)
@click.option("--force", is_flag=True, help="Replace a previous study in --out.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def study_stations(config, trials, attribution_trials, seed, out, quiet, force):
    """One station or several: the per-point uncertainty of the compensated machine, side by side.

    CONFIG states its stations in [[stations]] (default: the bundled example, the paper's machine from two laser
    trackers and two tracking interferometers; docs/user-guide.md, "Several stations"). The verification is
    simulated and identified from the first laser tracker alone and from all of them (every station's pose, or
    position and dead path, identified with the machine's errors), on the same machine with the same seed. Writes
    stations.md, .html and .json with a figure to --out. About 23 s of CPU with the defaults (27 s wall on 2
    shared cores; docs/performance.md).
    """
    _fresh_out(out, ("stations",), force)
    from .config import bundled_config, load_config
    from .report_study import stations_lines, stations_report
    from .study import stations_comparison

    cfg = load_config(config if config is not None else bundled_config("four_stations"))
    r = stations_comparison(cfg, trials=trials, attribution_trials=attribution_trials, seed=seed, progress=not quiet)
    md = stations_report(r, out)
    click.echo("\n".join(stations_lines(r)))
    click.echo(f"  report: {md} and {md.with_suffix('.html')}, data: {md.with_suffix('.json')}")


@study.command("station-placement")
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--stations", "k_max", type=click.IntRange(min=1, max=6), default=4, show_default=True,
              help="Largest number of stations in a set (every set of 1 .. this many is ranked).")
@click.option("--candidates", type=click.IntRange(min=1, max=24), default=12, show_default=True,
              help="Candidate stations, evenly on a circle around the mesh.")
@click.option("--kind", type=click.Choice(["xyz", "range"]), default="xyz", show_default=True,
              help="Laser trackers (xyz) or tracking interferometers (range).")
@click.option("--radius", default="2.5 m", show_default=True, help="Radius of the circle, from the mesh centre.")
@click.option("--height", default="0.5 m", show_default=True, help="Height of the circle above the mesh centre.")
@click.option("--angular", default=None, help="The candidates' angular u (k = 1), e.g. \"20 urad\" (default: [tracker]).")
@click.option("--distance", default=None, help="The candidates' range u (k = 1), e.g. \"0.2 um\" (default: [tracker]).")
@click.option("--distance-per-length", default=None,
              help="The candidates' range u per length (k = 1), e.g. \"0.3 um/m\" (default: [tracker]).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("station-placement"),
              show_default=True)
@click.option("--force", is_flag=True, help="Replace a previous study in --out.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def study_station_placement(config, k_max, candidates, kind, radius, height, angular, distance, distance_per_length,
                            out, quiet, force):
    """Where to put several stations: the set that minimises the per-point uncertainty of the compensated machine.

    Candidate stations stand evenly on a horizontal circle around the mesh (--radius, --height); every set of 1 to
    --stations of them is ranked by its largest u (k = 1) over the mesh points and axes, from the identification
    covariance over all the set's stations (their poses, or positions and dead paths, identified with the errors)
    with the stated tracker noise and repeatability of CONFIG (default: the built-in paper configuration). A chosen
    set then goes into [[stations]] for the full Monte Carlo (`mtbudget run`, `mtbudget study stations`).
    """
    _fresh_out(out, ("station-placement",), force)
    from .config import load_config
    from .errors import ConfigError
    from .report_study import station_placement_lines, station_placement_report
    from .scenario import build_scenario
    from .study import ring_candidates, station_placement
    from .units import to_internal

    if candidates < k_max:
        raise click.BadParameter(f"{candidates} candidates cannot make a set of {k_max}", param_hint="--candidates")
    r_mm = to_internal(radius, "mm", where="--radius", error=ConfigError)
    h_mm = to_internal(height, "mm", where="--height", error=ConfigError)
    if not 0 < r_mm <= 1e5 or abs(h_mm) > 1e5:
        raise click.BadParameter("radius must be positive and both at most 100 m", param_hint="--radius/--height")
    from .recording import uncertainty_problem

    noise = {}
    for name, text, unit in (("angular", angular, "rad"), ("distance", distance, "mm"),
                             ("distance_per_length", distance_per_length, "mm/mm")):
        if text is not None:
            noise[name] = to_internal(text, unit, where=f"--{name.replace('_', '-')}", error=ConfigError)
            problem = uncertainty_problem(f"tracker.{name}", noise[name])
            if problem:
                raise ConfigError(f"--{name.replace('_', '-')}: {problem}")
    sc = build_scenario(load_config(config))
    r = station_placement(sc, ring_candidates(sc, candidates, kind, r_mm, h_mm, noise), k_max, progress=not quiet)
    md = station_placement_report(r, out)
    click.echo("\n".join(station_placement_lines(r)))
    click.echo(f"  report: {md} and {md.with_suffix('.html')}, data: {md.with_suffix('.json')}")


def _readings(config, out, quiet, trials):
    """Every reading of the paper's figures side by side (docs/paper-reproduction.md), printed and written."""
    from .config import load_config
    from .progress import note
    from .report_study import readings_report, readings_text
    from .scenario import build_scenario
    from .study import paper_readings, readings_verdict

    from .progress import working

    note("every reading of the paper's figures side by side ...", not quiet)
    with working("readings", not quiet):
        r = paper_readings(build_scenario(load_config(config)), trials=trials)  # the run's own verifications
        md = readings_report(r, out)
    verdict = readings_verdict(r)
    with open(md, "a", encoding="utf-8") as fh:
        fh.write("\n" + verdict + "\n")
    click.echo("\n" + readings_text(r))
    click.echo(f"  tables: {md} and {md.with_suffix('.json')}")
    click.echo("\n" + verdict)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
