#!/usr/bin/env python3
"""`shoal pgo` vs GTSAM 4.3 (pip) on the public SE(3) pose graphs.

For every graph in ../shared/data/posegraphs (or --data) and each initialisation
(odometry = the file's vertices, chordal), runs `shoal pgo --json` and GTSAM's default
Levenberg-Marquardt (with the prior of gtsam_baseline.py), both --runs times, and prints a
markdown table: final E ours vs GTSAM (relative difference), LM iterations and median solve
time. GTSAM is run live when `import gtsam` works (same machine, same moment, fair timing);
otherwise (or with --baseline-only) the figures of gtsam_baseline.json are used.

Times: ours = `solve_time_s` (chordal init + LM, parsing excluded); GTSAM = optimize()
(odometry) or InitializePose3.initialize() + optimize() (chordal), graph loading excluded.

    cargo build --release && python3 benches/pgo_gtsam.py --shoal target/release/shoal
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
FILES = [
    "gtsam_pose3example.g2o",
    "gtsam_pose3example-grid.g2o",
    "tinyGrid3D.g2o",
    "smallGrid3D.g2o",
    "parking-garage.g2o",
    "sphere2500.g2o",
    "sphere_bignoise_vertex3.g2o",
    "torus3D.g2o",
    "cubicle.g2o",
]


def run_ours(shoal, path, init, runs):
    outs = []
    for _ in range(runs):
        p = subprocess.run([shoal, "pgo", "--graph", path, "--init", init, "--json"],
                           capture_output=True, text=True)
        if p.returncode != 0:
            return {"error": p.stderr.strip().splitlines()[-1] if p.stderr.strip() else "failed"}
        outs.append(json.loads(p.stdout))
    r = outs[-1]
    r["time_median_s"] = statistics.median(o["solve_time_s"] for o in outs)
    return r


def run_gtsam(path, init, runs):
    import gtsam
    import numpy as np
    graph, initial = gtsam.readG2o(path, True)
    first = sorted(initial.keys())[0]
    graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first),
                                     gtsam.noiseModel.Diagonal.Variances(
                                         np.array([1e-6] * 3 + [1e-4] * 3))))
    times, res, iters = [], None, 0
    for _ in range(runs):
        t0 = time.perf_counter()
        start = gtsam.InitializePose3.initialize(graph) if init == "chordal" else initial
        opt = gtsam.LevenbergMarquardtOptimizer(graph, start, gtsam.LevenbergMarquardtParams())
        res = opt.optimize()
        times.append(time.perf_counter() - t0)
        iters = opt.iterations()
    return {"final_cost": graph.error(res), "iterations": iters,
            "time_median_s": statistics.median(times)}


def from_baseline(baseline, name, init):
    for r in baseline["results"]:
        if r["file"] == name:
            sec = r["LM"] if init == "odometry" else r["chordal_LM"]
            if "exception" in sec:
                return {"error": sec["exception"][:60]}
            t = sec["time_median_s"] + (sec.get("init_time_s", 0.0) if init == "chordal" else 0.0)
            return {"final_cost": sec["final_gtsam_error"], "iterations": sec["iterations"],
                    "time_median_s": t}
    return {"error": "not in baseline"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shoal", default=os.path.join(HERE, "..", "target", "release", "shoal"))
    ap.add_argument("--data", default=None, help="posegraphs folder")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--baseline-only", action="store_true")
    ap.add_argument("--files", nargs="*", default=FILES)
    a = ap.parse_args()
    data = a.data or os.environ.get("SHOAL_DATA", os.path.join(HERE, "..", "..", "shared", "data"))
    if not a.data:
        data = os.path.join(data, "posegraphs")
    if not os.path.isdir(data):
        sys.exit(f"no pose graphs at {data}")
    baseline = json.load(open(os.path.join(data, "gtsam_baseline.json")))
    live = not a.baseline_only
    if live:
        try:
            import gtsam  # noqa: F401
        except ImportError:
            live = False
    print(f"GTSAM figures: {'live (this run)' if live else 'gtsam_baseline.json'}; "
          f"times = median of {a.runs}\n")
    print("| graph | init | E ours | E GTSAM | rel. diff | iters ours / GTSAM | time ours s | time GTSAM s | ours/GTSAM |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in a.files:
        path = os.path.join(data, name)
        if not os.path.exists(path):
            continue
        for init in ("odometry", "chordal"):
            ours = run_ours(a.shoal, path, init, a.runs)
            if live:
                try:
                    ref = run_gtsam(path, init, a.runs)
                except Exception as ex:  # e.g. cubicle chordal: IndeterminantLinearSystem
                    ref = {"error": type(ex).__name__}
            else:
                ref = from_baseline(baseline, name, init)
            eo = f"{ours['final_cost']:.9g}" if "error" not in ours else f"ERR {ours['error'][:50]}"
            eg = f"{ref['final_cost']:.9g}" if "error" not in ref else f"ERR {ref['error']}"
            if "error" in ours or "error" in ref:
                rel, ratio, it = "-", "-", "-"
            else:
                rel = f"{(ours['final_cost'] - ref['final_cost']) / ref['final_cost']:+.1e}"
                ratio = f"{ours['time_median_s'] / ref['time_median_s']:.2f}"
                it = f"{ours['iterations']} / {ref['iterations']}"
            to = f"{ours['time_median_s']:.4f}" if "error" not in ours else "-"
            tg = f"{ref['time_median_s']:.4f}" if "error" not in ref else "-"
            print(f"| {name} | {init} | {eo} | {eg} | {rel} | {it} | {to} | {tg} | {ratio} |",
                  flush=True)


if __name__ == "__main__":
    main()
