"""The comparison of an identification (`identify --json`) with the truth of a generated five-axis recording,
and an independent linearised fit of such a recording (issue 26).

The comparison is invariant under any datum or minimum-norm choice: where a parameter takes part in a null
direction (the tracker's rotation absorbs ECOC; A's zero and C's tilt about X trade, FORMAT-3 section 6), it is
compared through the identifiable combination c = e_i - (its projection onto the reported null directions),
c . (estimate - truth), with the bound sum_j |c_j| u_j (an upper bound of its standard uncertainty whatever the
correlations), so held (datum) parameters and free ones are judged alike.  The weights of `not_identifiable`
are read as components in the reported units (um, urad).

`linear_fit` is a second identification written with the generator's own chain (numeric Jacobian, full tracker
covariance, one Gauss-Newton step from the true pose and zero errors), in identify's JSON shape: the tests of
the comparison run against it, so they hold before mtbudget reads format 3.  No mtbudget code.
"""

from __future__ import annotations

import re

import numpy as np

import fiveaxis_generator as g


def key(name, iso=None) -> str:
    """ISO 230-7 rotary names with the letter O (readers accept the digit 0 too); others as mtbudget names them."""
    for n in (name, iso):
        if n and re.fullmatch(r"E[XYZABC][O0][ABC]", n):
            return n[:2] + "O" + n[3]
    return name


def estimates(result: dict):
    """({name: (value, u)}, [{name: weight}]) from identify --json."""
    est = {key(p["name"], p.get("iso")): (float(p["value"]), float(p["uncertainty"])) for p in result["parameters"]}
    combos = [{key(e["parameter"], e.get("iso")): float(e["weight"]) for e in combo}
              for combo in result.get("not_identifiable", [])]
    return est, combos


def null_basis(names, combos) -> np.ndarray:
    """An orthonormal basis (n, k) of the reported null directions."""
    if not combos:
        return np.zeros((len(names), 0))
    V = np.array([[c.get(n, 0.0) for n in names] for c in combos]).T
    U, s, _ = np.linalg.svd(V, full_matrices=False)
    return U[:, s > 1e-9 * s[0]]


def compare(result: dict, truth: dict, checked, k: float = 3.0):
    """[(name, z, text)] for each checked parameter: z = c.(estimate - truth) / sum |c_j| u_j through its
    identifiable combination c, or None where it lies wholly in a reported null direction (then `text` says
    whether it is named in not_identifiable)."""
    est, combos = estimates(result)
    names = sorted(set(est) | {n for c in combos for n in c} | set(checked))
    Q = null_basis(names, combos)
    value = np.array([est.get(n, (0.0, 0.0))[0] for n in names])  # a parameter held at its start value: 0
    u = np.array([est.get(n, (0.0, 0.0))[1] for n in names])
    true = np.array([truth["parameters"].get(n, 0.0) for n in names])
    out = []
    for name in checked:
        i = names.index(name)
        e = np.zeros(len(names))
        e[i] = 1.0
        c = e - Q @ (Q.T @ e)
        if c[i] < 1e-6:
            named = any(abs(cb.get(name, 0.0)) > 0 for cb in combos)
            out.append((name, None, "named in not_identifiable" if named else "in no reported null direction"))
            continue
        c = c / c[i]
        c[np.abs(c) < 1e-8] = 0.0  # rounding of the projection
        diff, bound = c @ (value - true), np.abs(c) @ u
        if name not in est:
            out.append((name, np.inf, "missing from parameters but identifiable"))
            continue
        z = diff / bound if bound > 0 else np.inf
        terms = " ".join(f"{c[j]:+.4g} {names[j]}" for j in np.flatnonzero(c))
        out.append((name, z, f"{terms}: estimate - truth {diff:+.3f} +- {bound:.3f} (k = 1, bound) "
                             f"[truth {truth['parameters'].get(name, 0.0):+.3f}]"))
    return out


def problems(result: dict, truth: dict, checked, k: float = 3.0) -> list:
    bad = []
    for name, z, text in compare(result, truth, checked, k):
        if z is None:
            if text != "named in not_identifiable":
                bad.append(f"{name}: {text}")
        elif not abs(z) <= k:
            bad.append(f"{name}: z = {z:+.2f}; {text}")
    return bad


def unknown_parameters(result: dict, machine: str) -> list:
    """Parameters of the identification the generator's model does not have (e.g. rotary Fourier terms): their
    truth is 0, but the generator's Jacobian cannot include them."""
    est, combos = estimates(result)
    return sorted(n for n in set(est) | {n for c in combos for n in c} if not g.known_parameter(n, machine))


def null_problems(result: dict, truth: dict) -> list:
    """Whether not_identifiable spans exactly the null space of the generator's Jacobian for this plan."""
    est, combos = estimates(result)
    names = sorted(set(est) | {n for c in combos for n in c})
    if unknown_parameters(result, truth["kind"]):
        return []  # not checkable here (the tests that need it skip on unknown_parameters)
    mine = g.null_space(truth, names)
    Q = np.linalg.svd(mine, full_matrices=False)[0] if mine.shape[1] else np.zeros((len(names), 0))
    bad = []
    for combo in combos:
        v = np.array([combo.get(n, 0.0) for n in names])
        off = np.linalg.norm(v - Q @ (Q.T @ v)) / np.linalg.norm(v)
        if off > 1e-3:
            bad.append(f"{combo} is not a null direction of the plan (off by {off:.2g} of its length)")
    if null_basis(names, combos).shape[1] != mine.shape[1]:
        bad.append(f"{len(combos)} combinations named ({null_basis(names, combos).shape[1]} independent) but the "
                   f"plan has {mine.shape[1]} null directions")
    return bad




# ------------------------------------------------------------------------------------------- a second fit
def _covariances(lt, noise):
    """Per-row 3 x 3 covariance of lt: spherical tracker noise plus isotropic repeatability (mm^2)."""
    r = np.linalg.norm(lt, axis=1)
    az, el = np.arctan2(lt[:, 1], lt[:, 0]), np.arcsin(lt[:, 2] / r)
    e_r = lt / r[:, None]
    e_az = np.stack([-np.sin(az), np.cos(az), 0 * az], axis=1)
    e_el = np.stack([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)], axis=1)
    ua = noise["angular_urad"] * 1e-6
    sd = np.stack([noise["dist_um"] * 1e-3 + noise["dist_ppm"] * 1e-6 * r, r * np.cos(el) * ua, r * ua], axis=1)
    B = np.stack([e_r, e_az, e_el], axis=2) * sd[:, None, :]
    return B @ np.transpose(B, (0, 2, 1)) + (noise["repeat_um"] * 1e-3) ** 2 * np.eye(3)


def linear_fit(truth: dict, lt_measured: np.ndarray, names: list, hold=(), min_norm=False) -> dict:
    """identify --json's shape from one weighted Gauss-Newton step at zero errors and the true pose.

    Datum: the parameters in `hold` are held at 0 (and, if they do not cover the null space, the rest by the
    pseudo-inverse); min_norm=True: minimum-norm solution in um / urad.  not_identifiable: the null space of
    the generator's Jacobian, one combination per direction."""
    m, plan, ranges, pose = g.setup_of(truth)
    lt0 = g.to_tracker(m.table_points(plan, {}, ranges), pose)
    J = g.jacobian(truth, names)  # um per um / urad (names, then the pose)
    C = _covariances(lt0, truth["noise"])
    L = np.linalg.cholesky(C * 1e6)  # um^2
    Linv = np.linalg.inv(L)
    M = len(lt0)
    y = np.einsum("mij,mj->mi", Linv, (lt_measured - lt0) * 1e3).ravel()
    Jw = np.einsum("mij,mjk->mik", Linv, J.reshape(M, 3, -1)).reshape(3 * M, -1)
    free = np.array([n not in hold for n in names] + [True] * 6)
    A = Jw[:, free]
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    U, s, Vt = np.linalg.svd(A / scale, full_matrices=False)
    keep = s > 1e-9 * s[0]
    pinv = (Vt[keep].T / s[keep]) @ U[:, keep].T / scale[:, None]
    x = pinv @ y
    cov = pinv @ pinv.T
    rank = int(keep.sum())
    res = y - A @ x
    value, u = np.zeros(len(names) + 6), np.zeros(len(names) + 6)
    value[free], u[free] = x, np.sqrt(np.diag(cov))
    null = g.null_space(truth, names, J=J)
    return {
        "chi2_per_dof": float(res @ res / (3 * M - rank)), "dof": 3 * M - rank, "converged": True,
        "parameters": [{"name": n, "iso": n, "value": float(value[i]), "uncertainty": float(u[i]),
                        "unit": "um" if n[:2] in ("EX", "EY", "EZ") or n[0] == "d" else "urad"}
                       for i, n in enumerate(names)],
        "not_identifiable": [[{"parameter": n, "iso": n, "weight": float(w)} for n, w in zip(names, v)
                              if abs(w) > 1e-9 * np.abs(v).max()] for v in null.T],
    }
