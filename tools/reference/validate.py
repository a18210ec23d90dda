#!/usr/bin/env python3
"""Checks ``mitsuba_reference.py`` against answers known in closed form; exits 1 on a failure.

Cases (each run with both estimators, ``nee`` and ``hemisphere``):

``furnace``
    ``voxrad generate furnace``: the closed unit cube, every wall emitting ``E`` = 1 with
    reflectance ``rho`` = 0.5, so ``B = E / (1 - rho) = 2`` and ``H = 2`` at every point inside.
    Probes: the 300 points ``voxrad generate --probes`` draws (like ``voxrad study``), all facing
    in, plus four facing out (nothing is outside: ``B = H = 0`` there).
``squares``
    ``voxrad generate parallel-squares``: an emitting unit square (``E`` = 1, ``Kd`` = 0) at
    z = 0 facing +z and a receiver (``rho`` = 0.5) at z = 1 facing it. At a receiver point the
    irradiance is ``E`` times the point-to-square form factor (the sum of four corner
    rectangles, ``(1 / 2 pi) [A / sqrt(1 + A^2) atan(B / sqrt(1 + A^2)) + (A <-> B)]``); the
    area-weighted mean of those over the receiver (6 x 6 Gauss-Legendre probes) must equal
    ``E * F`` with ``F`` the analytic parallel-squares form factor (Howell C-11, as
    ``voxrad::gen::parallel_squares_form_factor``). Sides: the emitter's front shows ``B = E``,
    its back ``B = 0``, the receiver's back ``B = 0`` (emission is one-sided, on the winding's
    front: this is the face-normal convention check).

Pass criteria, per probe: ``|B - B_exact| <= z * se + margin`` with ``margin = 2e-4 |B_exact|``
(single-precision geometry) and ``z`` the two-sided normal quantile for a family-wise false
alarm rate of 0.1 % over the case's probes (about 4.4 for 300 probes); per case: the
mean z-score within 4 / sqrt(N) and the root-mean-square z-score in [0.75, 1.3] (the
standard errors are neither optimistic nor pessimistic); the squares' quadrature mean within
3 standard errors + margin of ``rho E F``.

Usage: ``python3 tools/reference/validate.py [--voxrad PATH] [--paths N] [--out FILE]``.
Without ``--voxrad`` it runs ``cargo run --release --quiet --`` from the repository root.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from statistics import NormalDist

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
TOOL = os.path.join(HERE, "mitsuba_reference.py")


def voxrad(args, binary):
    cmd = [binary] if binary else ["cargo", "run", "--release", "--quiet", "--"]
    subprocess.run(cmd + args, check=True, cwd=ROOT)


def reference(obj, points, out, paths, estimator, seed):
    start = time.time()
    subprocess.run(
        [
            sys.executable,
            TOOL,
            obj,
            "--points",
            points,
            "--out",
            out,
            "--paths",
            str(paths),
            "--estimator",
            estimator,
            "--seed",
            str(seed),
            "--quiet",
        ],
        check=True,
    )
    data = np.genfromtxt(out, delimiter=",", names=True)
    return np.atleast_1d(data), time.time() - start


def write_points(path, rows):
    with open(path, "w", encoding="utf-8") as f:
        f.write("x,y,z,nx,ny,nz\n")
        for r in rows:
            f.write(",".join(repr(float(v)) for v in r) + "\n")


def corner_factor(a, b, c):
    """Form factor from a point to a parallel rectangle a x b at distance c, over its corner."""
    if a <= 0.0 or b <= 0.0:
        return 0.0
    x, y = a / c, b / c
    sx, sy = math.sqrt(1 + x * x), math.sqrt(1 + y * y)
    return (x / sx * math.atan(y / sx) + y / sy * math.atan(x / sy)) / (2 * math.pi)


def point_factor(px, py, side, c):
    """Point (px, py) at distance c below a parallel square [0, side]^2."""
    total = 0.0
    for a in (px, side - px):
        for b in (py, side - py):
            total += corner_factor(a, b, c)
    return total


def squares_factor(a, c):
    """Howell C-11 for two directly opposed a x a squares at distance c."""
    x = y = a / c
    sx, sy = math.sqrt(1 + x * x), math.sqrt(1 + y * y)
    log = 0.5 * math.log((1 + x * x) * (1 + y * y) / (1 + x * x + y * y))
    return (
        2
        / (math.pi * x * y)
        * (log + x * sy * math.atan(x / sy) + y * sx * math.atan(y / sx) - x * math.atan(x) - y * math.atan(y))
    )


class Checker:
    def __init__(self):
        self.failures = []
        self.lines = []

    def say(self, text):
        print(text, flush=True)
        self.lines.append(text)

    def fail(self, text):
        self.failures.append(text)
        self.say("FAIL: " + text)

    def probes(self, name, got, se, exact):
        """Per-probe and per-case checks; returns the z-scores."""
        n = len(got)
        zcrit = NormalDist().inv_cdf(1 - 0.001 / (2 * n))
        margin = 2e-4 * np.abs(exact)
        dev = got - exact
        bad = np.abs(dev) > zcrit * se + margin
        for k in np.flatnonzero(bad):
            self.fail(f"{name}: probe {k}: {got[k]:.6g} vs {exact[k]:.6g} (se {se[k]:.3g})")
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, dev / np.where(se > 0, se, 1), 0.0)
        z = z[se > 0]
        if len(z) >= 20:
            mean, rms = float(z.mean()), float(np.sqrt((z * z).mean()))
            if abs(mean) > 4 / math.sqrt(len(z)) or not 0.75 <= rms <= 1.3:
                self.fail(f"{name}: z-scores mean {mean:.3f}, rms {rms:.3f} over {len(z)} probes")
        return z


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--voxrad", help="the voxrad binary (default: cargo run --release)")
    parser.add_argument("--paths", type=int, default=50000, help="paths per probe")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", help="also write the report to this file")
    args = parser.parse_args()
    check = Checker()
    with tempfile.TemporaryDirectory() as tmp:
        # ---------------- furnace
        obj = os.path.join(tmp, "furnace.obj")
        pts = os.path.join(tmp, "furnace_points.csv")
        voxrad(["generate", "furnace", "--out", obj, "--probes", pts], args.voxrad)
        rows = np.genfromtxt(pts, delimiter=",", skip_header=1)
        outward = np.array(
            [[0.5, 0.5, 0.0, 0, 0, -1], [0.0, 0.3, 0.6, -1, 0, 0], [0.2, 1.0, 0.7, 0, 1, 0],
             [0.7, 0.4, 1.0, 0, 0, 1]], dtype=float,
        )
        rows = np.vstack([rows, outward])
        write_points(pts, rows)
        inside = np.arange(len(rows)) < len(rows) - len(outward)
        for est in ("nee", "hemisphere"):
            data, secs = reference(obj, pts, os.path.join(tmp, "f.csv"), args.paths, est, args.seed)
            for q in ("B", "H"):
                got = np.stack([data[f"{q}_{c}"] for c in "rgb"], axis=1)
                se = np.stack([data[f"se_{q}_{c}"] for c in "rgb"], axis=1)
                exact = np.where(inside[:, None], 2.0, 0.0) * np.ones_like(got)
                # The furnace is grey: one channel (the three are the same numbers).
                z = check.probes(f"furnace {est} {q}", got[:, 0], se[:, 0], exact[:, 0])
                g = got[inside, 0]
                s = se[inside, 0]
                pooled = float(np.mean(g))
                pooled_se = float(np.sqrt(np.sum(s * s)) / len(s))
                if abs(pooled - 2.0) > 3 * pooled_se + 4e-4:
                    check.fail(f"furnace {est} {q}: pooled mean {pooled:.6f} vs 2")
                check.say(
                    f"furnace [{est}] {q}: {inside.sum()} probes inside, exact 2: mean "
                    f"{pooled:.6f} (se of mean {pooled_se:.2g}), median relative se "
                    f"{np.median(s / 2.0):.2e}, max |z| {np.max(np.abs(z)):.2f}, rms z "
                    f"{np.sqrt(np.mean(z * z)):.3f}; outside probes {got[~inside].ravel().max():.3g} "
                    f"(exact 0); {args.paths} paths, {secs:.1f} s"
                )
        # ---------------- parallel squares
        obj = os.path.join(tmp, "squares.obj")
        voxrad(["generate", "parallel-squares", "--out", obj], args.voxrad)
        side, dist, emission, rho = 1.0, 1.0, 1.0, 0.5
        nodes, weights = np.polynomial.legendre.leggauss(6)
        nodes = 0.5 * (nodes + 1.0) * side
        weights = 0.5 * weights * side
        rows, w, exact_h = [], [], []
        for i, x in enumerate(nodes):
            for j, y in enumerate(nodes):
                rows.append([x, y, dist, 0, 0, -1])
                w.append(weights[i] * weights[j] / (side * side))
                exact_h.append(emission * point_factor(x, y, side, dist))
        rows.append([0.5, 0.5, dist, 0, 0, -1])
        exact_h.append(emission * point_factor(0.5, 0.5, side, dist))
        centre = len(rows) - 1
        f_analytic = squares_factor(side, dist)
        quad = float(np.dot(w, exact_h[:centre]))
        if abs(quad - emission * f_analytic) > 1e-6:
            check.fail(f"squares: quadrature of the point factor {quad} != analytic {f_analytic}")
        # Sides: receiver's back, emitter's front and back.
        sides = [([0.3, 0.6, dist, 0, 0, 1], 0.0, 0.0), ([0.4, 0.3, 0.0, 0, 0, 1], emission, None),
                 ([0.6, 0.7, 0.0, 0, 0, -1], 0.0, 0.0)]
        for r, _, _ in sides:
            rows.append(r)
        pts = os.path.join(tmp, "squares_points.csv")
        write_points(pts, rows)
        exact_b = np.concatenate([rho * np.array(exact_h), [s[1] for s in sides]])
        for est in ("nee", "hemisphere"):
            data, secs = reference(obj, pts, os.path.join(tmp, "s.csv"), 4 * args.paths, est, args.seed)
            got, se = data["B_r"], data["se_B_r"]
            recv = slice(0, centre + 1)
            check.probes(f"squares {est} B (receiver)", got[recv], se[recv], exact_b[recv])
            for k, (r, b_exact, _) in enumerate(sides):
                kk = centre + 1 + k
                if abs(got[kk] - b_exact) > 4 * se[kk] + 1e-6:
                    check.fail(f"squares {est}: side probe {r}: B {got[kk]} vs {b_exact}")
            mean = float(np.dot(w, got[:centre]))
            mean_se = float(np.sqrt(np.dot(np.square(w), np.square(se[:centre]))))
            target = rho * emission * f_analytic
            if abs(mean - target) > 3 * mean_se + 2e-4 * target:
                check.fail(f"squares {est}: receiver mean B {mean} vs {target}")
            check.say(
                f"squares [{est}]: receiver mean B {mean:.6f} (se {mean_se:.2g}) vs "
                f"rho E F = {target:.6f} (F = {f_analytic:.6f}); centre B {got[centre]:.6f} "
                f"(se {se[centre]:.2g}) vs {exact_b[centre]:.6f}; emitter front B "
                f"{got[centre + 2]:.4f} (exact 1), emitter back {got[centre + 3]:.3g}, receiver "
                f"back {got[centre + 1]:.3g} (exact 0); {4 * args.paths} paths, {secs:.1f} s"
            )
    status = "FAILED" if check.failures else "passed"
    check.say(f"validation {status} ({len(check.failures)} failures)")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write("\n".join(check.lines) + "\n")
    return 1 if check.failures else 0


if __name__ == "__main__":
    sys.exit(main())
