"""The ``mtbudget`` command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from . import __version__
from .errors import MtbudgetError


class _Group(click.Group):
    """Turn mtbudget's own errors into one-line messages and exit code 2."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except MtbudgetError as exc:
            click.echo(f"error: {exc}", err=True)
            ctx.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mtbudget")
def main():
    """Uncertainty budgets for machine-tool volumetric verification with a laser tracker.

    \b
    Start with:
      mtbudget simulate --out sim        simulate the built-in paper study into ./sim
      mtbudget identify sim              identify the machine's errors from it
      mtbudget identify --example null   the same on a bundled example recording

    Every command has --help. Quantities in configs and recordings carry units
    (pint syntax: "5 um", "20 degC", "0.8 um/m").
    """


@main.command()
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("mtbudget-simulation"),
              show_default=True, help="Folder to write the simulated recording into (created if missing).")
@click.option("--seed", type=int, default=None, help="Seed of the measurement noise (default: the config's seed).")
@click.option("--no-identify", is_flag=True, help="Only write the recording; skip the identification summary.")
def simulate(config, out, seed, no_identify):
    """Simulate a verification and write it as a recording.

    CONFIG is a TOML configuration (default: the built-in paper study,
    examples/paper_xfyz.toml). The folder gets recording.toml, points.csv
    and truth.json (what the simulation put in), in the format of
    docs/recording-format.md, so a simulation and a real recording can be
    compared point by point.
    """
    from .config import load_config
    from .recording import write_recording
    from .simulate import simulate as run

    cfg = load_config(config)
    rec, truth = run(cfg, seed)
    write_recording(rec, out, truth=truth)
    click.echo(f"wrote {len(rec)} simulated points of {cfg.name!r} ({cfg.machine}) to {out}/")
    if not no_identify:
        _print_identification(out)


def _print_identification(folder, as_json=False, max_degree=3, strategy="one-phase"):
    from .identify import Noise, Strategy, identify
    from .model import MeasurementModel
    from .recording import read_recording

    rec = read_recording(folder)
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    strat = Strategy.one_phase() if strategy == "one-phase" else Strategy.multi_phase()
    res = identify(model, rec.lt, Noise.of(rec), strat)
    u = res.u_theta()[0]
    summary = {
        "recording": rec.name,
        "points": len(rec),
        "chi2_per_dof": float(res.chi2_per_dof[0]),
        "dof": int(res.dof),
        "mean_error_before_um": float(res.mean_error_before[0] * 1e3),
        "mean_error_after_um": float(res.mean_error_after[0] * 1e3),
        "max_residual_um": float(res.max_residual[0] * 1e3),
        "converged": bool(res.converged[0]),
        "pose": dict(zip("DLHabd", map(float, res.pose[0]))),
        "parameters": [
            {"name": p.name, "value": float(v * (1e3 if p.unit == "mm" else 1e6)),
             "uncertainty": float(s * (1e3 if p.unit == "mm" else 1e6)), "unit": "um" if p.unit == "mm" else "urad"}
            for p, v, s in zip(model.errors.params, res.theta[0], u)
        ],
        "not_identifiable": [[{"parameter": n, "weight": w} for n, w in combo]
                             for combo in res.identifiability.combinations()],
    }
    if as_json:
        click.echo(json.dumps(summary, indent=1))
        return summary
    click.echo(f"identified {rec.name!r}: {len(rec)} points, {res.dof} degrees of freedom")
    click.echo(f"  chi-square per dof        {summary['chi2_per_dof']:.3f}  (1 = residuals match the stated uncertainties)")
    click.echo(f"  mean volumetric error     {summary['mean_error_before_um']:.2f} um before, "
               f"{summary['mean_error_after_um']:.2f} um after compensation (paper Eq. 27)")
    click.echo(f"  maximum residual          {summary['max_residual_um']:.2f} um")
    if summary["not_identifiable"]:
        click.echo("  not identifiable from this plan (held at their initial value):")
        for combo in res.identifiability.combinations():
            click.echo("    " + " ".join(f"{w:+.2f}*{n}" for n, w in combo))
    return summary


@main.command()
@click.argument("recording", required=False, type=click.Path(file_okay=False, path_type=Path))
@click.option("--example", type=click.Choice(["null", "thermal_x", "reversal_y", "tracker_drift"]),
              help="Use a bundled example recording instead of a folder.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (parameters with units and uncertainties).")
@click.option("--max-degree", type=int, default=3, show_default=True, help="Legendre degree of each error function.")
@click.option("--strategy", type=click.Choice(["one-phase", "multi-phase"]), default="one-phase", show_default=True,
              help="Optimisation strategy: all errors at once (the paper's choice) or pose, then translational, then all.")
def identify(recording, example, as_json, max_degree, strategy):
    """Identify the tracker pose and geometric errors of a recording.

    RECORDING is a folder with recording.toml and points.csv. Prints the
    chi-square per degree of freedom, the paper's mean volumetric error
    (Eq. 27) before and after compensation, and which error combinations the
    plan cannot identify.
    """
    from .config import example_recording

    if recording is None and example is None:
        raise click.UsageError("give a RECORDING folder or --example NAME")
    folder = example_recording(example) if example else recording
    _print_identification(folder, as_json, max_degree, strategy)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
