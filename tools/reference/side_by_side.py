#!/usr/bin/env python3
"""voxrad against a path tracer at equal error, on one machine, for a full-surface answer.

The speed issue asks how long a path tracer (Mitsuba 3, through ``mitsuba_reference.py``) takes
to give every surfel of a scene the error that a voxrad solve reaches. This script measures both
on the probes of a reference directory (``tests/data/reference/NAME``):

1. voxrad's error: ``voxrad probe`` on a solved result directory (``--result``), both the
   surfels' values and the gathered ones (``probe --gather``), against ``reference.csv``.
2. The path tracer's error and time: ``mitsuba_reference.py`` on the same probes with a few
   path counts (``--paths``, a seed other than the reference's), each timed whole.
3. Monte Carlo error falls as one over the square root of the paths, so the paths per point
   that reach voxrad's error are ``N (e_N / e_voxrad)^2``, fitted over the runs; the seconds per
   probe-path come from a straight-line fit of the runs' times (the scene's set-up is the
   intercept). Their product times the surfel count (``--surfels``, from the solve's report) is
   the path tracer's time for every surfel.

The error is the one ``voxrad study`` reports: the mean over the probes of ``|B - B_ref| /
B_ref`` with ``B`` summed over the three channels, leaving out the probes whose reference is
below 5 % of the median (dark corners, where relative errors mean little).

Example (the speed issue's Cornell setting)::

    voxrad solve examples/cornell_box.obj --resolution 256 --directions 589 \\
        --direct-directions 20000 --threads 2 --out out/cb256
    python3 tools/reference/side_by_side.py tests/data/reference/cornell \\
        --result out/cb256 --voxrad target/release/voxrad --paths 64,256,1024 --threads 2

Output: one line per run and the summary, on standard output.
"""

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time

DARK_FRACTION = 0.05
HERE = os.path.dirname(os.path.abspath(__file__))


def radiosity_sums(path):
    """B_r + B_g + B_b of every row of a probe or reference CSV, in order."""
    with open(path, newline="") as f:
        return [float(r["B_r"]) + float(r["B_g"]) + float(r["B_b"]) for r in csv.DictReader(f)]


def usable(reference):
    lit = sorted(reference)
    floor = lit[len(lit) // 2] * DARK_FRACTION
    return [r if r > floor else None for r in reference]


def mean_error(values, reference):
    errors = [abs(v - r) / r for v, r in zip(values, reference) if r is not None and r > 0.0]
    if not errors:
        sys.exit("no usable probe to compare")
    return sum(errors) / len(errors), len(errors)


def voxrad_errors(voxrad, result, points, reference):
    out = {}
    for label, extra in (("surfels", []), ("gathered", ["--gather"])):
        with tempfile.NamedTemporaryFile(suffix=".csv") as f:
            start = time.perf_counter()
            subprocess.run(
                [voxrad, "probe", result, "--points", points, "--out", f.name, *extra],
                check=True,
            )
            seconds = time.perf_counter() - start
            out[label] = (mean_error(radiosity_sums(f.name), reference)[0], seconds)
    return out


def mitsuba_run(scene, points, paths, seed, threads):
    with tempfile.NamedTemporaryFile(suffix=".csv") as f:
        start = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                os.path.join(HERE, "mitsuba_reference.py"),
                scene,
                "--points",
                points,
                "--out",
                f.name,
                "--paths",
                str(paths),
                "--seed",
                str(seed),
                "--threads",
                str(threads),
                "--quiet",
            ],
            check=True,
        )
        seconds = time.perf_counter() - start
        return radiosity_sums(f.name), seconds


def line_fit(xs, ys):
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx > 0 else 0.0
    return my - slope * mx, slope


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reference", help="a reference directory (scene.obj or the Cornell box)")
    parser.add_argument("--result", required=True, help="a directory written by voxrad solve")
    parser.add_argument("--voxrad", default="voxrad", help="the voxrad binary")
    parser.add_argument("--scene", help="the OBJ scene (default: REFERENCE/scene.obj)")
    parser.add_argument("--paths", default="64,256,1024", help="path counts per probe")
    parser.add_argument("--seed", type=int, default=7, help="seed of the path tracer's runs")
    parser.add_argument("--threads", type=int, default=0, help="the path tracer's threads")
    parser.add_argument("--surfels", type=int, help="surfels to price (default: the report's)")
    args = parser.parse_args()

    points = os.path.join(args.reference, "probes.csv")
    reference = usable(radiosity_sums(os.path.join(args.reference, "reference.csv")))
    scene = args.scene or os.path.join(args.reference, "scene.obj")
    with open(os.path.join(args.result, "report.json")) as f:
        report = json.load(f)
    surfels = args.surfels or report["surfels"]
    solve_seconds = report["seconds"]["total"]

    print(f"probes used: {mean_error(reference, reference)[1]} of {len(reference)}")
    ours = voxrad_errors(args.voxrad, args.result, points, reference)
    for label, (error, seconds) in ours.items():
        print(f"voxrad {label}: mean error {100 * error:.3f} % (probe {seconds:.1f} s)")
    print(f"voxrad solve: {solve_seconds:.1f} s for {surfels} surfels")

    runs = []
    for paths in [int(p) for p in args.paths.split(",")]:
        values, seconds = mitsuba_run(scene, points, paths, args.seed, args.threads)
        error, probes = mean_error(values, reference)
        runs.append((paths, error, seconds))
        print(f"path tracer {paths} paths: mean error {100 * error:.3f} % in {seconds:.1f} s")

    # Paths per point for error e: N (e_N / e)^2, averaged over the runs in log space.
    n = len(reference)
    intercept, per_path = line_fit([p * n for p, _, _ in runs], [s for _, _, s in runs])
    print(f"path tracer: {per_path * 1e6:.3f} us per probe-path, set-up {intercept:.1f} s")
    for label, (error, _) in ours.items():
        log_paths = [math.log(p * (e / error) ** 2) for p, e, _ in runs]
        needed = math.exp(sum(log_paths) / len(log_paths))
        every = needed * surfels * per_path
        print(
            f"at voxrad's {label} error {100 * error:.3f} %: {needed:.0f} paths per point, "
            f"{every:.0f} s for every surfel, {every / solve_seconds:.1f} times voxrad's solve"
        )


if __name__ == "__main__":
    main()
