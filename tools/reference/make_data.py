#!/usr/bin/env python3
"""Regenerates the committed reference data under ``tests/data/reference/``.

For every scene below: ``voxrad generate`` writes ``scene.obj``, ``scene.mtl``, ``probes.csv``
and ``surfaces.csv`` into ``tests/data/reference/<name>/`` (the Cornell box uses
``examples/cornell_box.obj`` and only gets its probes and labels written), then
``mitsuba_reference.py`` writes ``reference.csv``. Each run's figures (paths per probe, seed,
seconds, median and largest relative standard error of B, Mitsuba version and variant) are
appended to ``tests/data/reference/runs.csv`` (relative errors over the probes that see light;
``covered`` counts those that see none).

Usage: ``python3 tools/reference/make_data.py [--voxrad PATH] [--only NAME ...] [--scale F]``
(``--scale`` multiplies every scene's paths, for a quick trial into ``--root``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
TOOL = os.path.join(HERE, "mitsuba_reference.py")


def thin(light, t, tilted):
    name = f"thin-{light}-t{t}" + ("-tilted" if tilted else "")
    args = ["thin-slab", "--light", light, "--thickness", t]
    if tilted:
        args += ["--tilt", "20,10"]
    return name, args


# (name, generate arguments, paths per probe[, extra mitsuba_reference.py arguments])
SCENES = [
    ("cornell", ["cornell"], 500_000),
    ("office", ["office"], 1_000_000),
    ("window-room", ["window-room"], 300_000),
    ("corridor", ["corridor"], 1_200_000),
]
for _tilted in (False, True):
    for _light in ("side", "top"):
        for _t in ("0.5", "1", "0.3", "2"):
            SCENES.append(thin(_light, _t, _tilted) + (300_000,))
# Twins of the furnace hard cases (tests/hard_case_twins.rs). The white box's reflectance 0.999
# needs paths without Russian roulette (see mitsuba_reference.py, "Reflectance near 1"): 9,300
# bounces each, which leave out about 0.999^9300 = 9e-5 of B.
SCENES += [
    ("twin-white-box", ["hard-twin", "--twin", "white-box"], 2_000,
     ["--max-depth", "9300", "--rr-depth", "9300"]),
    ("twin-black-box", ["hard-twin", "--twin", "black-box"], 100_000),
    ("twin-slab", ["hard-twin", "--twin", "slab"], 200_000),
    ("twin-slab-tilted", ["hard-twin", "--twin", "slab-tilted"], 200_000),
]


def spread(ref):
    """Probe count, median and largest relative standard error of B (worst channel per probe) over the
    probes that see light, and the number that do not (B below 1e-4 of the median: probes
    covered by a solid, such as the Cornell box's floor points under the blocks). Where B is 0 at
    every probe (a black scene: B = E and no probe is on an emitter) the figures are those of the
    irradiance H instead."""
    d = np.genfromtxt(ref, delimiter=",", names=True)
    q = "B" if any(np.any(d[f"B_{c}"] > 0) for c in "rgb") else "H"
    b = np.stack([d[f"{q}_{c}"] for c in "rgb"], axis=1)
    se = np.stack([d[f"se_{q}_{c}"] for c in "rgb"], axis=1)
    lit = b.sum(axis=1) > 1e-4 * np.median(b.sum(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(b > 0, se / np.where(b > 0, b, 1), 0.0).max(axis=1)[lit]
    return len(b), float(np.median(rel)), float(rel.max()), int((~lit).sum())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--voxrad", help="the voxrad binary (default: cargo run --release)")
    parser.add_argument("--only", nargs="*", help="scene names to (re)make")
    parser.add_argument("--scale", type=float, default=1.0, help="multiplies the paths")
    parser.add_argument("--root", default=os.path.join(ROOT, "tests", "data", "reference"))
    parser.add_argument("--variant", default="llvm_ad_rgb")
    args = parser.parse_args()
    cmd = [args.voxrad] if args.voxrad else ["cargo", "run", "--release", "--quiet", "--"]
    import mitsuba

    runs = os.path.join(args.root, "runs.csv")
    if not os.path.exists(runs):
        os.makedirs(args.root, exist_ok=True)
        with open(runs, "w", encoding="utf-8") as f:
            f.write(
                "scene,probes,paths,seed,seconds,median_rel_se_B,max_rel_se_B,covered,"
                "mitsuba,variant,estimator\n"
            )
    for index, (name, gen, paths, *extra) in enumerate(SCENES):
        extra = extra[0] if extra else []
        if args.only and name not in args.only:
            continue
        paths = max(2, int(paths * args.scale))
        seed = 1000 + index
        out = os.path.join(args.root, name)
        os.makedirs(out, exist_ok=True)
        if name == "cornell":
            obj = os.path.join(ROOT, "examples", "cornell_box.obj")
            scratch = os.path.join(out, "scratch.obj")
            subprocess.run(
                cmd + ["generate", *gen, "--out", scratch, "--probes",
                       os.path.join(out, "probes.csv"), "--surfaces",
                       os.path.join(out, "surfaces.csv")],
                check=True, cwd=ROOT,
            )
            for ext in (".obj", ".mtl"):
                os.remove(scratch[:-4] + ext)
        else:
            obj = os.path.join(out, "scene.obj")
            subprocess.run(
                cmd + ["generate", *gen, "--out", obj, "--probes",
                       os.path.join(out, "probes.csv"), "--surfaces",
                       os.path.join(out, "surfaces.csv")],
                check=True, cwd=ROOT,
            )
        print(f"== {name}: {paths} paths per probe, seed {seed}", flush=True)
        start = time.time()
        ref = os.path.join(out, "reference.csv")
        subprocess.run(
            [sys.executable, TOOL, obj, "--points", os.path.join(out, "probes.csv"), "--out",
             ref, "--paths", str(paths), "--seed", str(seed), "--variant", args.variant, *extra],
            check=True,
        )
        seconds = time.time() - start
        count, median, largest, covered = spread(ref)
        with open(runs, "a", encoding="utf-8") as f:
            f.write(
                f"{name},{count},{paths},{seed},{seconds:.1f},{median:.3e},{largest:.3e},{covered},"
                f"{mitsuba.__version__},{args.variant},nee\n"
            )
        print(f"== {name}: {seconds:.1f} s, median relative se {100 * median:.3f} %, "
              f"max {100 * largest:.3f} %, {covered} covered probes", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
