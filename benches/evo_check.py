#!/usr/bin/env python3
"""Check that `shoal eval` agrees with the `evo` tool (evo_ape / evo_rpe).

For each case (generated TUM files, or the pair given with --est/--gt) and each alignment
(none, se3 = evo `-a`, sim3 = evo `-as`) this runs

    evo_ape tum GT EST [-a|-as] --save_results ...
    evo_rpe tum GT EST [-a|-as] --delta 1 --delta_unit f --save_results ...
    shoal eval --est EST --gt GT --align {none,se3,sim3} --json

and compares rmse, mean, median, std, min, max and sse. Exit status 1 when a relative
difference exceeds --tol (default 1e-6).

Requires `python3 -m pip install evo` (only evo's command-line tools are used: this script
is MIT OR Apache-2.0 like the rest of shoal and contains no evo code).

Usage:
    python3 benches/evo_check.py [--shoal target/release/shoal] [--est E --gt G] [--tol 1e-6]
"""
import argparse
import json
import math
import os
import random
import shutil
import subprocess
import sys
import tempfile
import zipfile

STATS = ["rmse", "mean", "median", "std", "min", "max", "sse"]
ALIGN_FLAGS = {"none": [], "se3": ["-a"], "sim3": ["-as"]}


def quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_axis_angle(axis, angle):
    n = math.sqrt(sum(c * c for c in axis)) or 1.0
    s = math.sin(angle / 2) / n
    return (math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s)


def quat_rotate(q, v):
    w, x, y, z = q
    p = quat_mul(quat_mul(q, (0.0, *v)), (w, -x, -y, -z))
    return p[1:]


def gt_pose(t):
    """A smooth 3D ground-truth trajectory with full 3D rotation."""
    p = (3.0 * math.cos(0.4 * t), 2.0 * math.sin(0.4 * t), 0.5 * math.sin(0.9 * t) + 0.05 * t)
    q = quat_mul(quat_axis_angle((0, 0, 1), 0.4 * t), quat_axis_angle((1, 0.3, 0), 0.3 * math.sin(t)))
    return p, q


def write_tum(path, rows):
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, p, q in rows:
            f.write(f"{t:.9f} {p[0]!r} {p[1]!r} {p[2]!r} {q[1]!r} {q[2]!r} {q[3]!r} {q[0]!r}\n")


def make_case(dirname, name, gt_hz, est_hz, n_gt, seed):
    """GT at gt_hz; estimate at est_hz with time jitter, dropped poses, a similarity
    transform (scale 0.4) and position / rotation noise."""
    rng = random.Random(seed)
    t0 = 1403715273.0
    gt_rows = []
    for i in range(n_gt):
        t = i / gt_hz
        p, q = gt_pose(t)
        gt_rows.append((t0 + t, p, q))
    dur = n_gt / gt_hz
    s = 0.4
    qs = quat_axis_angle((0.2, -0.5, 1.0), 0.8)
    ts = (1.5, -2.0, 0.3)
    est_rows = []
    for i in range(int(dur * est_hz)):
        if rng.random() < 0.1:
            continue  # dropped
        t = i / est_hz + rng.uniform(-0.003, 0.003) + 0.2
        p, q = gt_pose(t)
        p = tuple(c + rng.gauss(0, 0.03) for c in p)
        q = quat_mul(q, quat_axis_angle((rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 1)), rng.gauss(0, 0.02)))
        pr = quat_rotate(qs, p)
        p = tuple(s * pr[k] + ts[k] for k in range(3))
        q = quat_mul(qs, q)
        est_rows.append((t0 + t, p, q))
    gt_path = os.path.join(dirname, f"{name}_gt.txt")
    est_path = os.path.join(dirname, f"{name}_est.txt")
    write_tum(gt_path, gt_rows)
    write_tum(est_path, est_rows)
    return gt_path, est_path


def run_evo(tool, gt, est, align, workdir):
    out = os.path.join(workdir, f"{tool}_{align}_{os.path.basename(est)}.zip")
    if os.path.exists(out):
        os.remove(out)
    cmd = [tool, "tum", gt, est, *ALIGN_FLAGS[align], "--save_results", out, "--no_warnings"]
    if tool == "evo_rpe":
        cmd += ["--delta", "1", "--delta_unit", "f"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    with zipfile.ZipFile(out) as z:
        return json.loads(z.read("stats.json"))


def run_shoal(binary, gt, est, align):
    cmd = [binary, "eval", "--est", est, "--gt", gt, "--align", align, "--json"]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(res.stdout)


def rel_diff(a, b):
    m = max(abs(a), abs(b))
    return 0.0 if m < 1e-12 else abs(a - b) / m


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shoal", default="target/release/shoal", help="shoal binary (default %(default)s)")
    ap.add_argument("--est", help="estimate (TUM); with --gt instead of generated cases")
    ap.add_argument("--gt", help="ground truth (TUM)")
    ap.add_argument("--tol", type=float, default=1e-6, help="max relative difference")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--keep", help="keep the generated files in this folder")
    args = ap.parse_args()

    for tool in ("evo_ape", "evo_rpe"):
        if shutil.which(tool) is None:
            sys.exit(f"{tool} not found: python3 -m pip install evo")
    if not os.path.isfile(args.shoal):
        sys.exit(f"shoal binary {args.shoal} not found (cargo build --release, or pass --shoal)")

    workdir = args.keep or tempfile.mkdtemp(prefix="evo_check_")
    os.makedirs(workdir, exist_ok=True)
    if args.est and args.gt:
        cases = [("given", args.gt, args.est)]
    else:
        cases = [
            ("est_sparser", *make_case(workdir, "est_sparser", 20.0, 10.0, 400, args.seed)),
            ("est_denser", *make_case(workdir, "est_denser", 10.0, 30.0, 150, args.seed + 1)),
        ]

    worst = 0.0
    print(f"{'case':<12} {'align':<5} {'metric':<4} {'stat':<7} {'evo':>22} {'shoal':>22} {'rel diff':>10}")
    for name, gt, est in cases:
        for align in ("none", "se3", "sim3"):
            ours = run_shoal(args.shoal, gt, est, align)
            for metric, tool, key in (("APE", "evo_ape", "ate"), ("RPE", "evo_rpe", "rpe")):
                theirs = run_evo(tool, gt, est, align, workdir)
                for stat in STATS:
                    a, b = theirs[stat], ours[key][stat]
                    d = rel_diff(a, b)
                    worst = max(worst, d)
                    flag = "" if d <= args.tol else "  <-- FAIL"
                    print(f"{name:<12} {align:<5} {metric:<4} {stat:<7} {a:>22.15g} {b:>22.15g} {d:>10.2e}{flag}")
    print(f"\nmax relative difference: {worst:.3e} (tolerance {args.tol:g})")
    if not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)
    sys.exit(0 if worst <= args.tol else 1)


if __name__ == "__main__":
    main()
