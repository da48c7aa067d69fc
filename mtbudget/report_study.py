"""The paper's studies for people: placement and verification figures, the placement report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import make_folder
from .report import angles_label, write_html
from .units import factor

#: captions of the paper study's figures (the HTML reports show them under each figure)
STUDY_CAPTIONS = {
    "initial_errors": "Paper Fig. 12: initial error of the verification points (x, y, z and distance), before compensation",
    "final_errors": "Paper Fig. 14: error of the verification points left after compensation",
    "error_clouds": "Paper Figs. 13 and 15: error clouds at each mesh point before and after compensation, exaggerated",
    "compensation_mean": "compensation_mean: mean over the mesh of the compensated machine's error (paper Eq. 27 read as "
                         "the compensated machine, the study's default reading) over the simulated verifications, with a "
                         "normal fit",
    "placement_Y": "Paper Fig. 9: best tracker station of each test, tracker beside the machine (Y direction)",
    "placement_X": "Paper Fig. 10: best tracker station of each test, tracker in front of the machine (X direction)",
    "placement_histogram": "Paper Fig. 11: maximum point uncertainty u_p over the mesh at the best station of each test",
}


def placement_figures(res: dict, folder: Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    folder = make_folder(folder)
    figs = {}
    for name, d in res["directions"].items():
        loc, err = d["best_location"], d["max_error_um"]
        show = np.random.default_rng(0).choice(len(err), min(len(err), 20000), replace=False)
        fig = plt.figure(figsize=(7.5, 5.5))
        ax = fig.add_subplot(projection="3d")
        sc = ax.scatter(loc[show, 0], loc[show, 1], loc[show, 2], c=err[show], s=2, cmap="viridis")
        # the colour bar kept clear of the z axis' ticks and label (they overlapped)
        fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.14, label="maximum u_p over the mesh [µm]")
        ax.set_xlabel("x [mm]", labelpad=6)
        ax.set_ylabel("y [mm]", labelpad=6)
        ax.set_zlabel("z [mm]", labelpad=8)
        ax.set_title(f"best tracker station of each test: {name}-axis direction (paper Fig. {9 if name == 'Y' else 10})")
        p = folder / f"placement_{name}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        figs[f"placement_{name}"] = p
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, d in res["directions"].items():
        err = d["max_error_um"]
        ax.hist(err, bins=80, density=True, alpha=0.5, label=f"{name} direction (mean {err.mean():.1f} µm)")
        best = res["fits"][name][0]
        xs = np.linspace(err.min(), err.max(), 300)
        ax.plot(xs, getattr(stats, best["distribution"])(*best["parameters"]).pdf(xs), lw=1.5,
                label=f"{name}: best fit {best['distribution']} (KS {best['ks_distance']:.3f})")
    ax.set_xlabel("maximum error introduced by the tracker [µm]")
    ax.set_title("paper Fig. 11: maximum error at the best station of each test")
    ax.legend(fontsize=7)
    fig.tight_layout()
    p = folder / "placement_histogram.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["placement_histogram"] = p
    return figs


def placement_report(res: dict, j: dict, folder: Path) -> Path:
    """placement.md and placement.json in ``folder``: the study ``res`` and its summary ``j`` (study.placement_json)."""
    figs = placement_figures(res, folder)
    red = j["reduction"]
    lines = ["# Tracker placement study (paper Figs. 9-11)", "",
             f"{j['settings']['tests']} Monte Carlo tests per direction, {j['settings']['candidates']} candidate stations per "
             f"test; u_theta, u_phi ~ N({j['settings']['angular_mean_urad']:g}, {j['settings']['angular_sd_urad']:g}) urad, "
             f"u_d = {j['settings']['distance_um']:g} µm + {j['settings']['distance_per_length_um_per_m']:g} µm/m.", "",
             "| direction | tests | mean max error [µm] | std | 5 % | 95 % | best fit |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for k, d in j["directions"].items():
        e = d["max_error_um"]
        lines.append(f"| {k} | {d['tests']} | {e['mean']:.1f} | {e['std']:.1f} | {e['p05']:.1f} | {e['p95']:.1f} | "
                     f"{j['fits'][k][0]['distribution']} (KS {j['fits'][k][0]['ks_distance']:.3f}) |")
    lines += ["", f"The {red['better']} direction reduces the mean maximum error by {red['reduction']:.0%} against the "
              f"{red['worse']} direction ({red['mean_better_um']:.1f} vs {red['mean_worse_um']:.1f} µm); the paper reports "
              "about 30 %.", ""]
    lines += [f"![{STUDY_CAPTIONS.get(k, k)}]({p.name})" for k, p in figs.items()]
    (folder / "placement.md").write_text("\n".join(lines) + "\n")
    write_html(lines, folder, folder / "placement.html", "mtbudget tracker placement study")
    (folder / "placement.json").write_text(json.dumps(j, indent=1))
    return folder / "placement.md"


def verification_figures(res, init: np.ndarray, final: np.ndarray, mesh_pts: np.ndarray, folder: Path) -> dict:
    """Figs. 12-15: initial and final error clouds per point (um, from study.verification_clouds) and the final
    mean volumetric error distribution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    folder = make_folder(folder)
    figs = {}
    for name, data, fig_no in (("initial", init, 12), ("final", final, 14)):
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
        for i, a in enumerate("xyz"):
            axes[i].hist(data[..., i].ravel(), bins=80, density=True, color="#7aa6c2")
            axes[i].set_xlabel(f"{a} error [µm]")
        axes[3].hist(np.linalg.norm(data, axis=2).ravel(), bins=80, density=True, color="#c2a67a")
        axes[3].set_xlabel("distance error [µm]")
        # the clouds are recomputed for the study's first blocks: say how many of how many (it read "256" in a
        # 1000-verification study)
        fig.suptitle(f"{name} error of the verification points: the first {len(data)} of the study's {res.trials} "
                     f"simulated verifications (paper Fig. {fig_no})")
        fig.tight_layout()
        p = folder / f"{name}_errors.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        figs[f"{name}_errors"] = p
    fig = plt.figure(figsize=(13, 5.5))
    for j, (data, title) in enumerate(((init, "initial (paper Fig. 13)"), (final, "final (paper Fig. 15)"))):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        scale = 40.0 / max(np.abs(data).max(), 1e-9)  # mm of plot per um of error: clouds 40 mm across at most
        cloud = mesh_pts[None] + data * scale
        norm = np.linalg.norm(data, axis=2)
        sc = ax.scatter(cloud[..., 0].ravel(), cloud[..., 1].ravel(), cloud[..., 2].ravel(), c=norm.ravel(), s=1, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.1, label="error [µm]")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_zlabel("z [mm]")
        ax.set_title(f"{title}: error clouds of the first {len(data)} of {res.trials} verifications, "
                     f"exaggerated x{scale * factor('mm', 'um'):.0f}", fontsize=9)
    fig.tight_layout()
    p = folder / "error_clouds.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["error_clouds"] = p
    # compensation_mean (Eq. 27 read as the compensated machine, the number the console's first Eq. 27 line gives):
    # its distribution with a fitted normal, under its own name
    y = res.acc.scalar_samples("compensation_mean")
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(y, bins=50, density=True, color="#7aa6c2", label="MCM")
    mu, sd = y.mean(), y.std(ddof=1)
    xs = np.linspace(y.min(), y.max(), 200)
    ax.plot(xs, stats.norm.pdf(xs, mu, sd), "r", label=f"normal fit: mean {mu:.2f} µm, sigma {sd:.2f} µm")
    ax.set_xlabel("compensation_mean: mean error of the compensated machine over the mesh (Eq. 27) [µm]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = folder / "compensation_mean.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["compensation_mean"] = p
    return figs


# ----------------------------------------------------------------------------- every reading side by side
def _f(v, fmt="{:.1f}"):
    return "-" if v is None else fmt.format(v)


def _pct(v):
    return "-" if v is None else f"{100 * v:.0f} %"


def readings_lines(r: dict) -> list:
    """The side-by-side tables of :func:`mtbudget.study.paper_readings`, as Markdown lines (readable as text)."""
    ch = r["chosen"]
    tol = r["match_tolerance"]
    star = lambda name, chosen: ("* " if chosen else "") + name
    L = ["## How close the reproduction is: every reading of the paper's figures side by side", "",
         f"A number reproduces the paper's when it lies within {100 * tol:.0f} % of it (of a range's ends); 'matches' counts "
         "them. * marks the configured reading, the default being the one that matches most (docs/paper-reproduction.md); "
         "each other reading is one key of [placement] away (directions, eq23, eq27). sigma is the spread of the "
         "simulated values over the tests (a standard deviation, k = 1), not an uncertainty statement.", ""]
    p = r["placement"]
    L += [f"### Figs. 9-11, tracker placement: maximum u_p (Eq. 24, k = 1) over the mesh at the best station of "
          f"each test, µm; {p['tests']} tests per direction per row",
          "", "| reading: directions, Eq. 23 theta | Y mean | Y sigma | Y max | X mean | X sigma | X max | "
          "reduction X vs Y | Y max - X max | matches (of 4) |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
          "| paper | 60-80 | | | 40-60 | | | about 30 % | about 30 | |"]
    for name, row in p["rows"].items():
        d, e = name.split(", ")
        L.append(f"| {star(name, d == ch['directions'] and e == ch['eq23'])} | {row['Y_mean']:.1f} | {row['Y_sigma']:.1f} | "
                 f"{row['Y_max']:.1f} | {row['X_mean']:.1f} | {row['X_sigma']:.1f} | {row['X_max']:.1f} | "
                 f"{_pct(row['reduction'])} | {row['max_difference']:.1f} | {row['matches']} |")
    L += ["", "The maxima grow with the number of tests (the paper ran 100 000 per direction).", ""]
    q = r["eq23"]
    L += [f"### Eq. 23-24 at the paper's station: u_p (k = 1) over the {q['points']} mesh points, µm",
          "", "| theta of Eq. 23 | min | mean | sigma over the points | max | matches (of 1) |",
          "| --- | --- | --- | --- | --- | --- |", "| paper | | | | about 50 (its Fig. 10 station, like the final maximum) | |"]
    for name, row in q["readings"].items():
        L.append(f"| {star(name, name == ch['eq23'])} | {row['min']:.1f} | {row['mean']:.1f} | {row['sigma']:.1f} | "
                 f"{row['max']:.1f} | {row['matches']} |")
    c = q["largest_correlation"]
    L += ["", f"Eq. 23 keeps the variances only: the exact covariance at this station has a largest |correlation| "
          f"between Cartesian components of {c['min']:.2f}-{c['max']:.2f} per point (tracker frame).", ""]
    i = r["initial"]
    L += [f"### Fig. 13, initial errors (pose-only fit), {i['trials']} verifications, µm",
          "", "| | geometry: mean over the points of mean error vector length | its max | noise: mean 3-D RMS scatter per point | "
          "median ratio geometry/noise | points where geometry > noise | matches (of 1) |",
          "| --- | --- | --- | --- | --- | --- | --- |", "| paper | | | | | all (geometric errors greater than the noise) | |",
          f"| simulated | {i['geometry_mean_um']:.1f} | {i['geometry_max_um']:.1f} | {i['noise_mean_um']:.1f} | "
          f"{i['ratio_median']:.2f} | {_pct(i['share_geometry_dominated'])} | {i['matches']} |", ""]
    nt = r.get("normality")
    if nt:
        L += [f"### Figs. 12 and 14, how normal the errors look: Kolmogorov-Smirnov distance to a normal of the same "
              f"mean and sigma, {nt['samples']} point errors pooled (smaller is more normal; dimensionless)", "",
              "| errors | x | y | z | distance | matches (of 5) |", "| --- | --- | --- | --- | --- | --- |",
              "| paper | | | | | initial not normal; final normal, particularly the distance and y |"]
        for name, row in nt["rows"].items():
            m = "" if row["matches"] is None else row["matches"]
            L.append(f"| {name} | {row['x']:.3f} | {row['y']:.3f} | {row['z']:.3f} | {row['distance']:.3f} | {m} |")
        L += ["", "A final row matches once for each column below the initial row, and once if the distance and y "
              "are its two smallest. initial and compensated: machine frame; residual: tracker frame.", ""]
    e27 = r["eq27"]
    L += [f"### Figs. 14-15, Eq. 27 after compensation: {e27['trials']} verifications, µm (initial Eq. 27: "
          f"{e27['initial_mean_um']:.1f} µm)", "",
          "| reading | mean | sigma | mean + 2 sigma | max, 95 % of tests below | max of all | final / initial | "
          "matches (of 5) |", "| --- | --- | --- | --- | --- | --- | --- | --- |",
          "| paper | 13.77 | 5.02 | 23.81 | about 50 (a few tests) | | greatly minimized (< 0.5) | |"]
    for name, row in e27["rows"].items():
        L.append(f"| {star(name, name == ch['eq27'] + ', per test')} | {row['mean']:.2f} | {row['sigma']:.2f} | "
                 f"{row['bound']:.2f} | {row['max_p95']:.1f} | {row['max']:.1f} | {row['reduction']:.2f} | {row['matches']} |")
    L += ["", "per test: the mean over the points of each verification, spread over the verifications; pooled: every "
          "point of every verification as one sample. compensated: the distance error of the compensated machine "
          "(docs/measurand.md), rigid part removed; compensated_rigid: kept; residual: the fit residual.", ""]
    s = r.get("sensitivity")
    if s:
        L += [f"### Sensitivity: one change at a time from the configured readings ({s['tests']} placement tests per "
              f"direction, {s['trials']} verifications per row), µm",
              "", "| change | Fig. 11 Y mean | X mean | reduction | Eq. 27 mean | sigma | max, 95 % of tests below |",
              "| --- | --- | --- | --- | --- | --- | --- |",
              "| paper | 60-80 | 40-60 | about 30 % | 13.77 | 5.02 | about 50 |"]
        for name, row in s["rows"].items():
            L.append(f"| {name} | {_f(row['Y_mean'])} | {_f(row['X_mean'])} | {_pct(row['reduction'])} | "
                     f"{_f(row['eq27_mean'], '{:.2f}')} | {_f(row['eq27_sigma'], '{:.2f}')} | {_f(row['eq27_max_p95'])} |")
        L += ["", f"-: {s['note']}.", ""]
    return L


def readings_text(r: dict) -> str:
    return "\n".join(readings_lines(r))


def readings_report(r: dict, folder: Path) -> Path:
    """readings.md and readings.json in ``folder``: the side-by-side tables of study.paper_readings."""
    folder = make_folder(folder)
    (folder / "readings.md").write_text("# The paper's figures, every reading\n\n" + readings_text(r) + "\n")
    (folder / "readings.json").write_text(json.dumps(r, indent=1, default=float))
    return folder / "readings.md"


def stations_lines(r: dict) -> list:
    """The comparison of study.stations_comparison as text: per axis, u over the mesh for each variant, their ratio,
    and the budget's groups."""
    one, many = r["variants"][0], r["variants"][-1]
    lines = [f"Measurand: {r['measurand']}.",
             f"Standard uncertainty u per axis (k = 1), µm, from {one['trials']} Monte Carlo trials per variant "
             "(same machine, same seed):", "",
             f"  (a u from {one['trials']} trials is itself known to about {1 / np.sqrt(2 * (one['trials'] - 1)):.0%} "
             "relative, k = 1: a ratio of two to about "
             f"{np.sqrt(2) / np.sqrt(2 * (one['trials'] - 1)):.0%}; more trials with --trials)",
             "  " + "; ".join(f"{v['label']}: {v['kinds']}" for v in r["variants"]), "",
             f"  {'':<52}{'x':>10}{'y':>10}{'z':>10}"]
    for v in r["variants"]:
        sm = v["summary"]
        lines.append(f"  {v['label'] + ': RMS of u over the mesh':<52}" + "".join(f" {x:9.2f}" for x in sm["u_rms_over_mesh"]))
        lines.append(f"  {v['label'] + ': largest u':<52}" + "".join(f" {x:9.2f}" for x in sm["u_max"]))
    lines.append(f"  {'ratio ' + many['label'] + ' / ' + one['label'] + ', median over points':<52}"
                 + "".join(f" {x:9.2f}" for x in r["ratio_median"]))
    lines.append(f"  {'ratio, largest over points':<52}" + "".join(f" {x:9.2f}" for x in r["ratio_max"]))
    lines.append("")
    for v in r["variants"]:
        c = v["compensation_rms"]
        extra = f"; {v['not_converged']} trial(s) did not converge" if v["not_converged"] else ""
        lines.append(f"  {v['label']}: RMS over the mesh of the compensated machine's error (a trial's measurand "
                     f"summary) mean {c['mean']:.2f} µm, standard deviation {c['std']:.2f} µm (k = 1){extra}")
        if v.get("budget_groups"):
            shares = ", ".join(f"{g['group']} {g['share']:.0%}" for g in v["budget_groups"] if g["share"] > 0.005)
            inter = v.get("interaction_share")
            lines.append(f"    budget of the per-point variance by group: {shares}"
                         + (f"; interaction (not additive) {inter:+.0%}" if inter is not None else ""))
    return lines


def stations_figure(r: dict, folder: Path) -> Path:
    """u per point and axis, one station against several: one panel per axis, points in plan order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = make_folder(folder)
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for a, ax in enumerate(axes):
        for v in r["variants"]:
            u = np.asarray(v["u"])
            ax.plot(np.arange(len(u)), u[:, a], marker="o", ms=3, lw=1, label=v["label"])
        ax.set_ylabel(f"u({'xyz'[a]}) [µm], k = 1")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("mesh point (plan order)")
    return _save(fig, "Standard uncertainty of the compensated machine's error per point and axis: one station vs "
                      "several", folder / "stations_u.png")


def _save(fig, title: str, path: Path) -> Path:
    """Title, lay out, write (100 dpi) and close a figure of a study report."""
    import matplotlib.pyplot as plt

    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def stations_report(r: dict, folder: Path) -> Path:
    """stations.md, stations.html, stations.json and the figure in ``folder``."""
    p = stations_figure(r, folder)
    lines = ["# One station or several: the per-point uncertainty of the compensated machine", "",
             f"Measurand: {r['measurand']}. Every u is a standard uncertainty (k = 1) in µm, from "
             f"{r['variants'][0]['trials']} Monte Carlo trials per variant, the same machine and the same seed.", "",
             "| verified from | RMS of u over the mesh (x, y, z) | largest u (x, y, z) | compensation RMS, mean and "
             "standard deviation | budget of the per-point variance by group |", "| --- | --- | --- | --- | --- |"]
    for v in r["variants"]:
        sm, c = v["summary"], v["compensation_rms"]
        groups = ", ".join(f"{g['group']} {g['share']:.0%}" for g in v.get("budget_groups") or [] if g["share"] > 0.005)
        if v.get("interaction_share") is not None:
            groups += f", interaction (not additive) {v['interaction_share']:+.0%}"
        lines.append(f"| {v['label']} ({v['kinds']}) | {', '.join(f'{x:.2f}' for x in sm['u_rms_over_mesh'])} | "
                     f"{', '.join(f'{x:.2f}' for x in sm['u_max'])} | {c['mean']:.2f}, {c['std']:.2f} | "
                     f"{groups or 'not computed (attribution trials 0)'} |")
    lines += ["", f"Ratio of u, {r['variants'][-1]['label']} over {r['variants'][0]['label']}: median over the points "
              f"{', '.join(f'{x:.2f}' for x in r['ratio_median'])} (x, y, z), largest "
              f"{', '.join(f'{x:.2f}' for x in r['ratio_max'])}."]
    lines += ["", "| point | nominal x, y, z [mm] | " + " | ".join(f"u {v['label']} [µm] (x, y, z)" for v in r["variants"])
              + " |", "| --- | --- | " + " | ".join("---" for _ in r["variants"]) + " |"]
    for i, nom in enumerate(r["commanded"]):
        cells = [", ".join(f"{x:.2f}" for x in np.asarray(v["u"])[i]) for v in r["variants"]]
        at = angles_label({"angles": r["angles"][i]}) if r.get("angles") else ""  # five-axis: the point's rotary angles
        lines.append(f"| {i} | {', '.join(f'{x:g}' for x in nom)}{at} | " + " | ".join(cells) + " |")
    lines += ["", f"![u per point and axis, one station vs several]({p.name})"]
    (folder / "stations.md").write_text("\n".join(lines) + "\n")
    write_html(lines, folder, folder / "stations.html", "mtbudget: one station or several")
    (folder / "stations.json").write_text(json.dumps(r, indent=1, default=_jsonable))
    return folder / "stations.md"


def _jsonable(x):
    return x.tolist() if isinstance(x, np.ndarray) else float(x)


def station_placement_lines(r: dict) -> list:
    """The station placement study (study.station_placement) as text."""
    c = r["candidates"]
    lines = [f"Measurand: {r['measurand']}.",
             f"  {len(c)} candidate {c[0]['kind']} stations; every set of 1 to {r['per_k'][-1]['stations']} ranked by its "
             f"largest u (µm, k = 1) over the mesh points and axes ({r['seconds']:.1f} s):", "",
             f"  {'stations':>8} {'sets':>6} {'best':>8} {'median':>8} {'worst':>8}   best set (candidate numbers), RMS of u "
             "over the mesh (x, y, z)"]
    for k in r["per_k"]:
        if not k["identifying"]:
            lines.append(f"  {k['stations']:>8} {k['sets']:>6}   no set of {k['stations']} identifies what all the "
                         "candidates together identify")
            continue
        note = "" if k["identifying"] == k["sets"] else f"   ({k['sets'] - k['identifying']} sets identify too little)"
        lines.append(f"  {k['stations']:>8} {k['sets']:>6} {k['best_max_u']:8.2f} {k['median_max_u']:8.2f} "
                     f"{k['worst_max_u']:8.2f}   {', '.join(str(i) for i in k['best'])}: "
                     f"({', '.join(f'{x:.2f}' for x in k['best_rms_u'])}){note}")
    nz = c[0]["noise"]
    lines += ["", "  every candidate ranked with the stated noise (k = 1): " + ", ".join(
        f"{v:g} {u}" for v, u in ((nz.get("angular_urad"), "µrad"), (nz["distance_um"], "µm"),
                                  (nz["distance_per_length_um_per_m"], "µm/m")) if v is not None)
              + " (--angular, --distance, --distance-per-length; default [tracker])",
              "  candidates (x, y, z in mm, machine frame):"]
    lines += [f"    {i}: {', '.join(f'{v:.0f}' for v in cd['place'][:3])}" for i, cd in enumerate(c)]
    lines += ["  (GUF from the stated noise: the Monte Carlo of a chosen set, `mtbudget run` with its [[stations]], adds "
              "the other sources)"]
    best = [k for k in r["per_k"] if k["identifying"]]
    if best:
        lines += ["", f"  the best set of {best[-1]['stations']}, to paste into a configuration:"]
        lines += ["    " + ln for ln in stations_toml([c[i] for i in best[-1]["best"]])]
    return lines


def stations_toml(cands: list) -> list:
    """[[stations]] tables of candidate stations ({"kind", "place", "noise"}), with their noise if not [tracker]'s."""
    out = []
    for cd in cands:
        p = cd["place"]
        out.append("[[stations]]")
        out.append(f'kind = "{cd["kind"]}"')
        if cd["kind"] == "xyz":
            out += [f'{k} = "{v:.1f} mm"' for k, v in zip("DLH", p[:3])]
            out += [f'{k} = "{np.degrees(v):.4f} deg"' for k, v in zip("abd", p[3:6])]
        else:
            out.append("position = [" + ", ".join(f'"{v:.1f} mm"' for v in p[:3]) + "]")
        nz = cd.get("noise") or {}
        if "angular_urad" in nz:
            out.append(f'angular = "{nz["angular_urad"]:g} urad"')
        if nz:
            out += [f'distance = "{nz["distance_um"]:g} um"', f'distance_per_length = "{nz["distance_per_length_um_per_m"]:g} um/m"']
    return out


def station_placement_figure(r: dict, folder: Path) -> Path:
    """Top view: the candidates, the mesh, and the best set for each number of stations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = make_folder(folder)
    cand = np.array([cd["place"][:3] for cd in r["candidates"]])
    mesh = np.asarray(r["mesh_points"])
    n = len(r["per_k"])
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.8), squeeze=False)
    for ax, k in zip(axes[0], r["per_k"]):
        if not k["identifying"]:
            ax.set_title(f"{k['stations']} station(s): none identifies enough", fontsize=9)
            ax.scatter(cand[:, 0], cand[:, 1], s=18, facecolors="none", edgecolors="k")
            continue
        ax.scatter(mesh[:, 0], mesh[:, 1], s=6, c="grey", label="mesh")
        ax.scatter(cand[:, 0], cand[:, 1], s=18, facecolors="none", edgecolors="k", label="candidates")
        b = cand[k["best"]]
        ax.scatter(b[:, 0], b[:, 1], s=60, c="C3", marker="^", label="best set")
        for i, p in zip(k["best"], b):
            ax.annotate(str(i), p[:2], textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_title(f"{k['stations']} station(s): largest u {k['best_max_u']:.1f} µm", fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("y [mm]")
    shown = [ax for ax, k in zip(axes[0], r["per_k"]) if k["identifying"]]
    if shown:
        shown[0].legend(fontsize=7, loc="best")
    return _save(fig, "Best set of stations per number of stations (top view; u: k = 1, largest over points and "
                      "axes)", folder / "station_placement.png")


def station_placement_report(r: dict, folder: Path) -> Path:
    """station_placement.md, .html, .json and the figure in ``folder``."""
    p = station_placement_figure(r, folder)
    c = r["candidates"]
    lines = ["# Where to put several stations", "",
             f"Measurand: {r['measurand']}. Every set of 1 to {r['per_k'][-1]['stations']} of {len(c)} candidate "
             f"{c[0]['kind']} stations, ranked by its largest u (µm, k = 1) over the mesh points and axes.", "",
             "| stations | sets | best | median | worst | best set | RMS of u over the mesh (x, y, z) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for k in r["per_k"]:
        if not k["identifying"]:
            lines.append(f"| {k['stations']} | {k['sets']} | - | - | - | no set identifies enough | |")
            continue
        lines.append(f"| {k['stations']} | {k['sets']} | {k['best_max_u']:.2f} | {k['median_max_u']:.2f} | "
                     f"{k['worst_max_u']:.2f} | {', '.join(str(i) for i in k['best'])} | "
                     f"{', '.join(f'{x:.2f}' for x in k['best_rms_u'])} |")
    lines += ["", "| candidate | x, y, z [mm] |", "| --- | --- |"]
    lines += [f"| {i} | {', '.join(f'{v:.0f}' for v in cd['place'][:3])} |" for i, cd in enumerate(c)]
    best = [k for k in r["per_k"] if k["identifying"]]
    if best:
        lines += ["", f"The best set of {best[-1]['stations']}, to paste into a configuration:", "", "```toml"]
        lines += stations_toml([c[i] for i in best[-1]["best"]]) + ["```"]
    lines += ["", f"![Best set of stations per number of stations]({p.name})"]
    (folder / "station_placement.md").write_text("\n".join(lines) + "\n")
    write_html(lines, folder, folder / "station_placement.html", "mtbudget: where to put several stations")
    (folder / "station_placement.json").write_text(json.dumps(r, indent=1, default=_jsonable))
    return folder / "station_placement.md"
