#!/usr/bin/env python3
"""The calibration-vs-scipy benchmark, scipy side.

Solves the same identification problem as calib-core's `identify_ls` on the dataset exported by
`cargo run -p calib-core --release --example export_dataset -- --out DIR`, with
`scipy.optimize.least_squares`, the way a competent user would:

* the same model: standard D-H (eq. 1 of the paper), `T_i = Rz(q_i + theta_i) Tz(d_i) Tx(a_i)
  Rx(alpha_i)`, 28 parameters in calib-core's order (a1..a7, d1..d7, alpha1..alpha7,
  theta1..theta7);
* the same residual: calib-core's tool-frame pose error (`calib-core/src/model.rs`,
  `pose_error`), `e = [R_m^T (p_a - p_m); log(R_m^T R_a)]`, 6 rows per sample;
* kinematics vectorised with numpy over all samples (no Python loop over samples);
* the analytic Jacobian `de/dx = -M(e) J` (calib-core's `fk_jacobian` and `error_jacobian`,
  re-derived here in numpy), or scipy's '2-point' finite differences (what pybotics does);
* `x_scale='jac'` (scipy's column scaling, the counterpart of calib-core's), the same starting
  point (Table 1) and matching tolerances: `ftol=1e-15` (calib-core stops when the cost gain
  is below 1e-15 of the cost), `xtol=1e-12` (calib-core: largest step below 1e-12),
  `gtol=1e-15` (calib-core has no gradient test; this keeps scipy from stopping earlier on it);
* both 'trf' (scipy's default) and 'lm' (MINPACK's Levenberg-Marquardt).

Every variant runs `--repeats` times; each run's time covers `least_squares` only (not the CSV
read) and is the process CPU time (`time.process_time`, as calib-core's side measures it, so
that other processes sharing the core do not count); the wall-time median is reported too.
One JSON object per line goes to stdout. Run it on one core with BLAS threads at 1
(`cargo xtask bench` does: `taskset -c 0`, `OPENBLAS_NUM_THREADS=1` and friends).
"""

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy
from scipy.optimize import least_squares

N = 7
P = 4 * N


def load(directory):
    data = np.loadtxt(directory / "samples.csv", delimiter=",", skiprows=1)
    q = np.ascontiguousarray(data[:, :N])
    ra = data[:, N : N + 9].reshape(-1, 3, 3)
    pa = np.ascontiguousarray(data[:, N + 9 : N + 12])
    with open(directory / "tables.csv", newline="") as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["index"]))
    start = np.array([float(r["start"]) for r in rows])
    truth = np.array([float(r["truth"]) for r in rows])
    assert start.shape == (P,) and truth.shape == (P,), "tables.csv must hold 28 parameters"
    return q, ra, pa, start, truth


def link(a, alpha, d, theta, q):
    """Link transforms of one joint for every sample: R (K,3,3), p (K,3)."""
    ct, st = np.cos(q + theta), np.sin(q + theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = ct
    r[:, 0, 1] = -st * ca
    r[:, 0, 2] = st * sa
    r[:, 1, 0] = st
    r[:, 1, 1] = ct * ca
    r[:, 1, 2] = -ct * sa
    r[:, 2, 0] = 0.0
    r[:, 2, 1] = sa
    r[:, 2, 2] = ca
    p = np.stack([a * ct, a * st, np.full_like(q, d)], axis=1)
    return r, p


def unpack(x):
    return x[0:N], x[N : 2 * N], x[2 * N : 3 * N], x[3 * N : 4 * N]


def fk(x, q):
    a, d, alpha, theta = unpack(x)
    r = np.broadcast_to(np.eye(3), (q.shape[0], 3, 3))
    p = np.zeros((q.shape[0], 3))
    for i in range(N):
        ri, pi = link(a[i], alpha[i], d[i], theta[i], q[:, i])
        p = p + np.einsum("kij,kj->ki", r, pi)
        r = r @ ri
    return r, p


def log_so3(r):
    """Rotation vectors of rotation matrices (K,3,3); calib-core's `log_so3` away from pi."""
    v = 0.5 * np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)
    c = 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0)
    th = np.arctan2(s, c)
    if th.size and th.max() >= np.pi - 1e-3:
        raise ValueError("pose error rotation near pi: outside what this vectorised log handles")
    factor = np.where(th < 1e-3, 1.0 + th * th / 6.0, th / np.where(s > 0.0, s, 1.0))
    return v * factor[:, None]


def pose_error(rm, pm, ra, pa):
    """e = [R_m^T (p_a - p_m); log(R_m^T R_a)] per sample, (K,6)."""
    ep = np.einsum("kji,kj->ki", rm, pa - pm)
    er = log_so3(np.swapaxes(rm, 1, 2) @ ra)
    return np.concatenate([ep, er], axis=1)


def skew(w):
    z = np.zeros(w.shape[0])
    return np.stack(
        [np.stack([z, -w[:, 2], w[:, 1]], 1), np.stack([w[:, 2], z, -w[:, 0]], 1), np.stack([-w[:, 1], w[:, 0], z], 1)], 1
    )


def fk_jacobian(x, q):
    """Tool pose and the identification Jacobian (K,6,28): tool-frame twists of unit parameter
    changes (calib-core's `fk_jacobian`, backward pass over the chain)."""
    a, d, alpha, theta = unpack(x)
    k = q.shape[0]
    jac = np.empty((k, 6, P))
    ur = np.broadcast_to(np.eye(3), (k, 3, 3))
    up = np.zeros((k, 3))
    ex = np.array([1.0, 0.0, 0.0])
    zero = np.zeros(3)
    for i in reversed(range(N)):
        sa, ca = np.sin(alpha[i]), np.cos(alpha[i])
        zl = np.array([0.0, sa, ca])
        twists = [(ex, zero), (zl, zero), (zero, ex), (np.array([0.0, a[i] * ca, -a[i] * sa]), zl)]
        for kind, (v, w) in enumerate(twists):
            col = kind * N + i
            jac[:, :3, col] = np.einsum("kji,kj->ki", ur, np.cross(w, up) + v)
            jac[:, 3:, col] = np.einsum("kji,j->ki", ur, w)
        ri, pi = link(a[i], alpha[i], d[i], theta[i], q[:, i])
        up = np.einsum("kij,kj->ki", ri, up) + pi
        ur = ri @ ur
    return ur, up, jac


def error_jacobian(e):
    """M(e) (K,6,6) with d pose_error(M exp(xi), A) = -M(e) d xi (calib-core's `error_jacobian`)."""
    k = e.shape[0]
    m = np.zeros((k, 6, 6))
    m[:, :3, :3] = np.eye(3)
    m[:, :3, 3:] = -skew(e[:, :3])
    er = e[:, 3:]
    th = np.linalg.norm(er, axis=1)
    ts = np.where(th < 1e-4, 1.0, th)
    c = np.where(th < 1e-4, 1.0 / 12.0 + th * th / 720.0, 1.0 / (ts * ts) - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)))
    kk = skew(er)
    m[:, 3:, 3:] = np.eye(3) - 0.5 * kk + c[:, None, None] * (kk @ kk)
    return m


class Problem:
    def __init__(self, q, ra, pa):
        self.q, self.ra, self.pa = q, ra, pa

    def residuals(self, x):
        rm, pm = fk(x, self.q)
        return pose_error(rm, pm, self.ra, self.pa).ravel()

    def jacobian(self, x):
        rm, pm, j = fk_jacobian(x, self.q)
        e = pose_error(rm, pm, self.ra, self.pa)
        return -(error_jacobian(e) @ j).reshape(-1, P)

    def y(self, x):
        """The paper's objective (eq. 10): sum over samples of the pose-error 2-norm."""
        return float(np.linalg.norm(self.residuals(x).reshape(-1, 6), axis=1).sum())

    def cost(self, x):
        r = self.residuals(x)
        return float(r @ r)


VARIANTS = {
    "trf-analytic": dict(method="trf", analytic=True),
    "lm-analytic": dict(method="lm", analytic=True),
    "trf-2point": dict(method="trf", analytic=False),
    "lm-2point": dict(method="lm", analytic=False),
}


def solve(problem, x0, method, analytic):
    return least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian if analytic else "2-point",
        method=method,
        x_scale="jac",
        ftol=1e-15,
        xtol=1e-12,
        gtol=1e-15,
    )


def accuracy(problem, x, truth):
    err = np.abs(x - truth)
    return {
        "cost": problem.cost(x),
        "y": problem.y(x),
        "err_a": float(err[0:N].max()),
        "err_d": float(err[N : 2 * N].max()),
        "err_alpha": float(err[2 * N : 3 * N].max()),
        "err_theta": float(err[3 * N : 4 * N].max()),
        "err_norm": float(np.linalg.norm(x - truth)),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="dataset folders written by export_dataset (k1000, ...)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated: " + ", ".join(VARIANTS))
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    for v in variants:
        if v not in VARIANTS:
            sys.exit(f"scipy_ls.py: unknown variant {v!r}; known: {', '.join(VARIANTS)}")
    for directory in args.dirs:
        q, ra, pa, start, truth = load(directory)
        problem = Problem(q, ra, pa)
        k = q.shape[0]
        # The analytic Jacobian against central differences at the start (a model self-check).
        jac = problem.jacobian(start)
        fd = np.empty_like(jac)
        for p in range(P):
            h = np.zeros(P)
            h[p] = 1e-6
            fd[:, p] = (problem.residuals(start + h) - problem.residuals(start - h)) / 2e-6
        print(
            json.dumps(
                {
                    "bench": "scipy-check",
                    "k": k,
                    "python": sys.version.split()[0],
                    "numpy": np.__version__,
                    "scipy": scipy.__version__,
                    "jac_max_abs_diff": float(np.abs(jac - fd).max()),
                    "jac_max_abs": float(np.abs(jac).max()),
                    "cost_start": problem.cost(start),
                    "y_start": problem.y(start),
                }
            ),
            flush=True,
        )
        for name in variants:
            spec = VARIANTS[name]
            times, walls = [], []
            for _ in range(args.repeats):
                c0, w0 = time.process_time(), time.perf_counter()
                res = solve(problem, start, **spec)
                times.append(time.process_time() - c0)
                walls.append(time.perf_counter() - w0)
            out = {
                "bench": "scipy",
                "variant": name,
                "k": k,
                "median_s": float(np.median(times)),
                "runs_s": times,
                "wall_median_s": float(np.median(walls)),
                "nfev": int(res.nfev),
                "njev": int(res.njev) if res.njev is not None else None,
                "status": int(res.status),
                "message": res.message,
            }
            out.update(accuracy(problem, res.x, truth))
            print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
