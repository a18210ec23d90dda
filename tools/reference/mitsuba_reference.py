#!/usr/bin/env python3
"""Path-traced reference radiosity at probe points, computed with Mitsuba 3.

This tool gives voxrad an answer that does not come from voxrad. It reads an OBJ + MTL scene with
voxrad's conventions, builds the same scene in Mitsuba 3 (a renderer written elsewhere), and for
every probe row ``x,y,z,nx,ny,nz`` of a CSV file estimates, with a Monte Carlo standard error,

* ``H``: the irradiance arriving at the surface point ``p`` from the hemisphere around ``n``;
* ``B = E_side + rho * H``: the radiosity leaving the surface at ``p`` on the side facing ``n``.

Conventions (the same as voxrad's README, "Units and conventions"):

* MTL ``Kd`` is the diffuse reflectance ``rho`` per RGB channel, ``Ke`` the *emitted radiosity*
  ``E`` per channel (power per area), so Mitsuba's emitter radiance is ``Ke / pi``.
* A triangle's front is the side ``(v1 - v0) x (v2 - v0)`` points to. Mitsuba's geometric normal
  is the same cross product (checked by ``validate.py``), and its ``area`` emitter emits from the
  front only, which is what voxrad does. Every surface reflects on both sides (``twosided`` around
  ``diffuse``), emitters included.
* Polygons are fan-triangulated; no smoothing normals are used (flat faces).

Estimators (``--estimator``):

``nee`` (default)
    ``H = H_direct + H_indirect``. ``H_direct`` samples a point on the emitters with Mitsuba's own
    emitter sampling (``Scene.sample_emitter_direction`` with a visibility test) and weights it by
    ``max(0, n . d)``. ``H_indirect`` draws cosine-weighted directions around ``n`` from
    ``p + eps n``, traces each with Mitsuba's ``path`` integrator (unbounded depth, Russian
    roulette), and subtracts the emission of the first surface hit (which ``H_direct`` already
    counts), so ``H_indirect = pi * mean(L_reflected)``. Both halves are unbiased; the sum is
    much less noisy than the plain estimator when lamps are small.
``hemisphere``
    The plain estimator: cosine-weighted directions traced with the ``path`` integrator,
    ``H = pi * mean(L_i)``. Kept as a cross-check of ``nee`` (``validate.py`` runs both).

Reflectance near 1 (``--max-depth``, ``--rr-depth``): Mitsuba's Russian roulette keeps a path
with probability ``q = min(max throughput, 0.95)`` and divides its throughput by ``q``; where the
reflectance is above ``sqrt(0.95) = 0.975`` everywhere the throughput of a surviving path grows
without bound and the estimator's variance is infinite (its standard errors mean nothing). For
such scenes turn the roulette off and truncate instead: ``--max-depth D --rr-depth D`` traces
every path to depth ``D``, and the light that needs more bounces, a fraction of about
``rho^D`` of ``B``, is left out (``D`` = 9,300 leaves out 1e-4 at ``rho`` 0.999). A path then
costs ``D`` bounces, but its many vertices also make it a better sample.

One "path" of a probe is one sample of each half. The standard errors are the sample standard
deviation over the paths divided by ``sqrt(paths)`` (paths are independent).

The probe's own material (``rho``, and ``E`` when ``n`` looks at the emitting front) is found by
tracing a short ray from ``p + delta n`` towards ``-n`` and mapping the Mitsuba shape that it hits
back to its MTL material; a probe that is not on a surface is an error (exit status 2).

All samples of many probes run in one wavefront (``--wavefront`` lanes per pass). Output: a CSV
with header ``x,y,z,nx,ny,nz,B_r,B_g,B_b,se_B_r,se_B_g,se_B_b,H_r,H_g,H_b,se_H_r,se_H_g,se_H_b,paths``.
Progress and the seconds taken go to standard error.

Example::

    python3 tools/reference/mitsuba_reference.py scene.obj --points probes.csv \\
        --out reference.csv --paths 1000000 --seed 1

    # reflectance 0.999: no roulette, paths of 9,300 bounces
    python3 tools/reference/mitsuba_reference.py box.obj --points probes.csv \\
        --out reference.csv --paths 2000 --max-depth 9300 --rr-depth 9300

Needs ``pip install mitsuba drjit numpy``; the LLVM variants need ``libllvm`` (Debian:
``libllvm19``). Without it, ``--variant scalar_rgb`` works (much slower, one ray at a time).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

HEADER = (
    "x,y,z,nx,ny,nz,B_r,B_g,B_b,se_B_r,se_B_g,se_B_b,"
    "H_r,H_g,H_b,se_H_r,se_H_g,se_H_b,paths"
)


class InputError(Exception):
    """Bad input: a message naming the file (and the line where there is one)."""


# ------------------------------------------------------------------------------------------------
# OBJ / MTL reading (only what voxrad's scenes use: v, f, usemtl, mtllib; newmtl, Kd, Ke).


def parse_mtl(path: str) -> dict[str, dict[str, list[float]]]:
    """Materials of an MTL file: name -> {'Kd': [r, g, b], 'Ke': [r, g, b]} (missing -> 0)."""
    materials: dict[str, dict[str, list[float]]] = {}
    current = None
    try:
        handle = open(path, encoding="utf-8")
    except OSError as e:
        raise InputError(f"{path}: cannot read the MTL file: {e}") from e
    with handle:
        for number, raw in enumerate(handle, 1):
            words = raw.split("#", 1)[0].split()
            if not words:
                continue
            key = words[0]
            if key == "newmtl":
                if len(words) < 2:
                    raise InputError(f"{path}:{number}: newmtl without a name")
                current = " ".join(words[1:])
                materials[current] = {"Kd": [0.0, 0.0, 0.0], "Ke": [0.0, 0.0, 0.0]}
            elif key in ("Kd", "Ke"):
                if current is None:
                    raise InputError(f"{path}:{number}: {key} before any newmtl")
                try:
                    values = [float(w) for w in words[1:4]]
                except ValueError as e:
                    raise InputError(f"{path}:{number}: {key} needs numbers: {e}") from e
                if len(values) == 1:
                    values = values * 3
                if len(values) != 3 or not all(math.isfinite(v) for v in values):
                    raise InputError(f"{path}:{number}: {key} needs 1 or 3 finite numbers")
                materials[current][key] = values
    return materials


def parse_obj(path: str):
    """Triangles of an OBJ file, grouped by material.

    Returns ``(vertices, groups, materials)``: ``vertices`` an (N, 3) float64 array, ``groups``
    a dict material name -> list of (i0, i1, i2) vertex indices (polygons fan-triangulated,
    zero-area triangles dropped), ``materials`` the merged MTL table.
    """
    vertices: list[list[float]] = []
    groups: dict[str, list[tuple[int, int, int]]] = {}
    materials: dict[str, dict[str, list[float]]] = {}
    base = os.path.dirname(os.path.abspath(path))
    current = None
    try:
        handle = open(path, encoding="utf-8")
    except OSError as e:
        raise InputError(f"{path}: cannot read the OBJ file: {e}") from e
    with handle:
        for number, raw in enumerate(handle, 1):
            words = raw.split("#", 1)[0].split()
            if not words:
                continue
            key = words[0]
            if key == "v":
                try:
                    xyz = [float(w) for w in words[1:4]]
                except ValueError as e:
                    raise InputError(f"{path}:{number}: bad vertex: {e}") from e
                if len(xyz) != 3 or not all(math.isfinite(c) for c in xyz):
                    raise InputError(f"{path}:{number}: a vertex needs 3 finite coordinates")
                vertices.append(xyz)
            elif key == "f":
                if current is None:
                    raise InputError(f"{path}:{number}: a face before any usemtl")
                idx = []
                for w in words[1:]:
                    try:
                        k = int(w.split("/", 1)[0])
                    except ValueError as e:
                        raise InputError(f"{path}:{number}: bad face index '{w}'") from e
                    k = k - 1 if k > 0 else len(vertices) + k
                    if not 0 <= k < len(vertices):
                        raise InputError(f"{path}:{number}: face index '{w}' out of range")
                    idx.append(k)
                if len(idx) < 3:
                    raise InputError(f"{path}:{number}: a face needs at least 3 vertices")
                for j in range(1, len(idx) - 1):
                    groups.setdefault(current, []).append((idx[0], idx[j], idx[j + 1]))
            elif key == "usemtl":
                current = " ".join(words[1:])
            elif key == "mtllib":
                for name in words[1:]:
                    materials.update(parse_mtl(os.path.join(base, name)))
    verts = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    for name in groups:
        if name not in materials:
            raise InputError(f"{path}: material '{name}' is used but not defined in any mtllib")
    # Drop zero-area triangles (voxrad's voxelizer drops them too).
    for name, tris in groups.items():
        t = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        cross = np.cross(verts[t[:, 1]] - verts[t[:, 0]], verts[t[:, 2]] - verts[t[:, 0]])
        groups[name] = t[np.linalg.norm(cross, axis=1) > 0.0]
    groups = {k: v for k, v in groups.items() if len(v)}
    if not groups:
        raise InputError(f"{path}: the scene has no triangle with a non-zero area")
    return verts, groups, materials


def read_probes(path: str) -> np.ndarray:
    """Probe rows ``x,y,z,nx,ny,nz`` (a non-numeric first line is a header); normals normalised."""
    rows = []
    try:
        handle = open(path, encoding="utf-8")
    except OSError as e:
        raise InputError(f"{path}: cannot read the points file: {e}") from e
    with handle:
        for number, raw in enumerate(handle, 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = [f.strip() for f in line.split(",")]
            try:
                values = [float(f) for f in fields[:6]]
            except ValueError:
                if not rows and number == 1:
                    continue  # header
                raise InputError(f"{path}:{number}: expected x,y,z,nx,ny,nz numbers") from None
            if len(values) != 6 or not all(math.isfinite(v) for v in values):
                raise InputError(f"{path}:{number}: expected 6 finite numbers")
            rows.append(values)
    if not rows:
        raise InputError(f"{path}: no probe rows")
    probes = np.asarray(rows, dtype=np.float64)
    length = np.linalg.norm(probes[:, 3:6], axis=1)
    if np.any(length == 0.0):
        bad = int(np.argmax(length == 0.0))
        raise InputError(f"{path}: probe {bad + 1} has a zero normal")
    probes[:, 3:6] /= length[:, None]
    return probes


# ------------------------------------------------------------------------------------------------
# Mitsuba scene


def load_mitsuba(variant: str):
    """Imports Mitsuba with ``variant``; falls back to ``scalar_rgb`` if an LLVM variant fails."""
    import drjit as dr  # noqa: F401
    import mitsuba as mi

    try:
        mi.set_variant(variant)
        # Force the back end to initialise now, so a missing libLLVM shows up here.
        if not variant.startswith("scalar"):
            _ = mi.Float([1.0]) + 1.0
    except Exception as e:  # noqa: BLE001 (any failure of the back end)
        if variant == "scalar_rgb":
            raise
        print(f"variant {variant} unavailable ({e}); using scalar_rgb", file=sys.stderr)
        mi.set_variant("scalar_rgb")
    return mi


def build_scene(mi, verts, groups, materials):
    """One Mitsuba mesh per material; returns (scene, {shape id: material name})."""
    import drjit as dr

    shapes = {}
    for k, (name, tris) in enumerate(sorted(groups.items())):
        kd = materials[name]["Kd"]
        ke = materials[name]["Ke"]
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(
            {
                "type": "twosided",
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": kd}},
            }
        )
        if any(e > 0.0 for e in ke):
            radiance = [e / math.pi for e in ke]
            props["emitter"] = mi.load_dict(
                {"type": "area", "radiance": {"type": "rgb", "value": radiance}}
            )
        # Each mesh gets its own compact vertex list (only the vertices it uses).
        used, local = np.unique(tris.ravel(), return_inverse=True)
        mesh = mi.Mesh(
            f"m{k}",
            vertex_count=len(used),
            face_count=len(tris),
            has_vertex_normals=False,
            has_vertex_texcoords=False,
            props=props,
        )
        params = mi.traverse(mesh)
        # The buffers' own types: mi.Float / mi.UInt32 in vectorised variants, dynamic arrays in
        # the scalar ones.
        float_buffer = type(params["vertex_positions"])
        index_buffer = type(params["faces"])
        params["vertex_positions"] = float_buffer(verts[used].astype(np.float32).ravel())
        params["faces"] = index_buffer(local.astype(np.uint32).ravel())
        params.update()
        shapes[f"m{k}"] = (mesh, name)
    scene_dict = {"type": "scene"}
    for key, (mesh, _) in shapes.items():
        scene_dict[key] = mesh
    scene = mi.load_dict(scene_dict)
    ids = {}
    for shape in scene.shapes():
        if mi.variant().startswith("scalar"):
            ids[shape.id()] = shapes[shape.id()][1]
        else:
            ids[int(shape_id(mi, dr, mi.ShapePtr(shape))[0])] = shapes[shape.id()][1]
    return scene, ids


def shape_id(mi, dr, ptr):
    """Integer identity (registry index) of Mitsuba shape pointers, as a numpy array."""
    return np.asarray(dr.reinterpret_array(mi.UInt32, ptr), dtype=np.int64).reshape(-1)


# ------------------------------------------------------------------------------------------------
# Probes


def offsets(probes: np.ndarray, verts: np.ndarray):
    """Offset off the surface for ray origins, and the lookup distance, in scene units."""
    scale = 1.0 + float(np.max(np.abs(verts)))
    eps = 1e-5 * scale
    return eps, 50.0 * eps


def lanes(mi, arr: np.ndarray, cls):
    """An (n, 3) numpy array as a Mitsuba 3-vector array (vectorised variants)."""
    a = np.ascontiguousarray(arr.T, dtype=np.float32)
    return cls(mi.Float(a[0]), mi.Float(a[1]), mi.Float(a[2]))


def identify(mi, scene, ids, materials, probes, eps, delta, path):
    """Each probe's material, rho and E (E only if n looks at the emitting front)."""
    import drjit as dr

    p, n = probes[:, :3], probes[:, 3:6]
    origin = p + delta * n
    count = len(probes)
    hits, t, dots = [], [], []
    if mi.variant().startswith("scalar"):
        for k in range(count):
            ray = mi.Ray3f(mi.Point3f(*origin[k]), mi.Vector3f(*(-n[k])))
            si = scene.ray_intersect(ray)
            ok = bool(si.is_valid())
            hits.append(si.shape.id() if ok else None)
            t.append(float(si.t) if ok else math.inf)
            dots.append(float(dr.dot(si.n, mi.Vector3f(*n[k]))) if ok else 0.0)
        t, dots = np.array(t), np.array(dots)
    else:
        ray = mi.Ray3f(lanes(mi, origin, mi.Point3f), lanes(mi, -n, mi.Vector3f))
        si = scene.ray_intersect(ray)
        valid = np.asarray(si.is_valid(), dtype=bool).reshape(-1)
        hits = np.where(valid, shape_id(mi, dr, si.shape), -1)
        t = np.where(valid, np.asarray(si.t, dtype=np.float64).reshape(-1), math.inf)
        dots = np.asarray(dr.dot(si.n, lanes(mi, n, mi.Vector3f)), dtype=np.float64).reshape(-1)
    names, rho, emit = [], np.zeros((count, 3)), np.zeros((count, 3))
    for k in range(count):
        if hits[k] not in ids or abs(t[k] - delta) > 0.5 * delta:
            raise InputError(
                f"{path}: probe {k + 1} at {tuple(p[k])} is not on a surface "
                f"(a ray towards -n from {delta:g} above it hit at distance {t[k]:g})"
            )
        name = ids[hits[k]]
        names.append(name)
        rho[k] = materials[name]["Kd"]
        if dots[k] > 0.0:
            emit[k] = materials[name]["Ke"]
    return names, rho, emit


def frames(n: np.ndarray):
    """Orthonormal tangents (s, t) for each unit normal (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def sample_pass(mi, scene, integrator, sampler, origin, n, s, t, estimator):
    """One sample per lane of the irradiance estimate; returns a (3, lanes) float64 array."""
    import drjit as dr

    o = lanes(mi, origin, mi.Point3f)
    nn = lanes(mi, n, mi.Vector3f)
    ss = lanes(mi, s, mi.Vector3f)
    tt = lanes(mi, t, mi.Vector3f)
    local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
    d = dr.normalize(ss * local.x + tt * local.y + nn * local.z)
    ray = mi.Ray3f(o, d)
    if estimator == "nee":
        # Direct part by emitter sampling from the probe.
        it = dr.zeros(mi.Interaction3f, len(origin))
        it.p = o
        it.n = mi.Normal3f(nn)
        it.t = mi.Float(0.0)
        ds, spec = scene.sample_emitter_direction(it, sampler.next_2d(), True)
        direct = spec * dr.maximum(dr.dot(nn, ds.d), 0.0)
        # Indirect part: the path integrator's radiance minus the first hit's own emission.
        si = scene.ray_intersect(ray)
        first = si.emitter(scene).eval(si, si.is_valid())
        radiance, _, _ = integrator.sample(scene, sampler, ray)
        h = direct + math.pi * (radiance - first)
    else:
        radiance, _, _ = integrator.sample(scene, sampler, ray)
        h = math.pi * radiance
    dr.eval(h)
    return np.asarray(h, dtype=np.float64).reshape(3, -1)


def sample_pass_scalar(mi, scene, integrator, sampler, origin, n, s, t, estimator):
    """``sample_pass`` one lane at a time (the scalar variant has no wavefronts)."""
    import drjit as dr

    out = np.zeros((3, len(origin)))
    for k in range(len(origin)):
        o = mi.Point3f(*origin[k])
        nn, ss, tt = mi.Vector3f(*n[k]), mi.Vector3f(*s[k]), mi.Vector3f(*t[k])
        local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
        d = dr.normalize(ss * local.x + tt * local.y + nn * local.z)
        ray = mi.Ray3f(o, d)
        h = mi.Color3f(0.0)
        if estimator == "nee":
            it = mi.Interaction3f()
            it.p, it.n, it.t = o, mi.Normal3f(nn), 0.0
            ds, spec = scene.sample_emitter_direction(it, sampler.next_2d(), True)
            h += spec * max(float(dr.dot(nn, ds.d)), 0.0)
            si = scene.ray_intersect(ray)
            if si.is_valid() and si.emitter(scene) is not None:
                h -= math.pi * si.emitter(scene).eval(si)
        radiance, _, _ = integrator.sample(scene, sampler, ray)
        h += math.pi * radiance
        out[:, k] = np.asarray(h, dtype=np.float64).reshape(3)
        sampler.advance()
    return out


def estimate(
    mi, scene, probes, eps, paths, seed, wavefront, estimator, log, max_depth=-1, rr_depth=5
):
    """Mean and standard error of H per probe: arrays (P, 3), (P, 3)."""
    count = len(probes)
    n = probes[:, 3:6]
    origin = probes[:, :3] + eps * n
    s, t = frames(n)
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": rr_depth})
    scalar = mi.variant().startswith("scalar")
    per_pass = max(1, min(paths, wavefront // count)) if not scalar else 1
    total = np.zeros((count, 3))
    total_sq = np.zeros((count, 3))
    done = 0
    start = time.time()
    passes = math.ceil(paths / per_pass)
    for k in range(passes):
        m = min(per_pass, paths - done)
        rep = lambda a: np.repeat(a, m, axis=0)  # noqa: E731 (lane = probe * m + sample)
        sampler = mi.load_dict({"type": "independent"})
        # Distinct, well-mixed seed per pass (the sampler hashes it with the lane index).
        sampler.seed((seed * 0x9E3779B1 + k * 0x85EBCA77 + 1) & 0x7FFFFFFF, count * m)
        fn = sample_pass_scalar if scalar else sample_pass
        h = fn(mi, scene, integrator, sampler, rep(origin), rep(n), rep(s), rep(t), estimator)
        h = h.reshape(3, count, m)
        total += h.sum(axis=2).T
        total_sq += (h * h).sum(axis=2).T
        done += m
        elapsed = time.time() - start
        if log and (k + 1 == passes or k % max(1, passes // 20) == 0):
            rate = done * count / max(elapsed, 1e-9)
            print(
                f"  pass {k + 1}/{passes}: {done} paths per probe, {elapsed:.1f} s, "
                f"{rate / 1e6:.2f} M paths/s",
                file=sys.stderr,
                flush=True,
            )
    mean = total / done
    var = np.maximum(total_sq / done - mean * mean, 0.0) * done / max(done - 1, 1)
    return mean, np.sqrt(var / done)


def write_rows(path, probes, h, se_h, rho, emit, paths):
    b = emit + rho * h
    se_b = rho * se_h
    lines = [HEADER]
    for k in range(len(probes)):
        values = list(probes[k]) + list(b[k]) + list(se_b[k]) + list(h[k]) + list(se_h[k])
        lines.append(",".join(repr(float(v)) for v in values) + f",{paths}")
    text = "\n".join(lines) + "\n"
    if path in (None, "-"):
        sys.stdout.write(text)
    else:
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description="Path-traced (Mitsuba 3) reference radiosity B and irradiance H at probe "
        "points of an OBJ + MTL scene, with voxrad's conventions (Kd = reflectance, Ke = emitted "
        "radiosity, emitters one-sided on the winding's front, surfaces two-sided).",
        epilog="Output columns: " + HEADER,
    )
    parser.add_argument("scene", help="the OBJ file (its mtllib is read beside it)")
    parser.add_argument("--points", required=True, help="CSV of probe rows x,y,z,nx,ny,nz")
    parser.add_argument("--out", default="-", help="output CSV (default: standard output)")
    parser.add_argument("--paths", type=int, default=100000, help="paths per probe")
    parser.add_argument("--seed", type=int, default=1, help="random seed")
    parser.add_argument(
        "--variant", default="llvm_ad_rgb", help="Mitsuba variant (falls back to scalar_rgb)"
    )
    parser.add_argument(
        "--estimator",
        choices=["nee", "hemisphere"],
        default="nee",
        help="nee: emitter sampling for direct light plus path-traced indirect light "
        "(default); hemisphere: path-traced cosine-weighted directions only",
    )
    parser.add_argument(
        "--wavefront", type=int, default=1 << 20, help="lanes per pass (all probes together)"
    )
    parser.add_argument(
        "--max-depth",
        type=int,
        default=-1,
        help="longest path the path integrator traces (-1: unbounded, the default)",
    )
    parser.add_argument(
        "--rr-depth",
        type=int,
        default=5,
        help="depth at which Russian roulette starts (default 5; set it to --max-depth to turn "
        "it off, see 'Reflectance near 1' above)",
    )
    parser.add_argument("--threads", type=int, default=0, help="worker threads (0: all)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)
    if args.paths < 2:
        parser.error("--paths must be at least 2 (the standard error needs two samples)")
    start = time.time()
    try:
        verts, groups, materials = parse_obj(args.scene)
        probes = read_probes(args.points)
        mi = load_mitsuba(args.variant)
        import drjit as dr

        if args.threads > 0 and not mi.variant().startswith("scalar"):
            dr.set_thread_count(args.threads)
        scene, ids = build_scene(mi, verts, groups, materials)
        eps, delta = offsets(probes, verts)
        names, rho, emit = identify(mi, scene, ids, materials, probes, eps, delta, args.points)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    log = not args.quiet
    if log:
        triangles = sum(len(t) for t in groups.values())
        print(
            f"{args.scene}: {triangles} triangles, {len(groups)} materials; "
            f"{len(probes)} probes; Mitsuba {mi.__version__} {mi.variant()}; "
            f"{args.paths} paths per probe, estimator {args.estimator}, seed {args.seed}",
            file=sys.stderr,
        )
        counts = {}
        for name in names:
            counts[name] = counts.get(name, 0) + 1
        print("  probes per material: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
              file=sys.stderr)
    traced = time.time()
    h, se_h = estimate(
        mi, scene, probes, eps, args.paths, args.seed, args.wavefront, args.estimator, log,
        args.max_depth, args.rr_depth,
    )
    write_rows(args.out, probes, h, se_h, rho, emit, args.paths)
    if log:
        b = emit + rho * h
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(b > 0, rho * se_h / np.where(b > 0, b, 1.0), -np.inf).max(axis=1)
        rel = rel[np.isfinite(rel)]
        med = float(np.median(rel)) if len(rel) else float("nan")
        print(
            f"done: {time.time() - traced:.1f} s tracing, {time.time() - start:.1f} s in all; "
            f"median relative standard error of B (worst channel) {100 * med:.3f} %",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
