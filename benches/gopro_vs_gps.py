#!/usr/bin/env python3
"""Compare `shoal run` trajectories of the GoPro clip with the drone's GPS track.

For each `--traj NAME=DIR_OR_FILE` (a run's output folder, whose `trajectory_c0.txt` and
`report.json` are read, or a TUM file `t x y z qx qy qz qw`), the camera positions are
matched by time with `karma_position_enu.csv` (GPS/EKF at 4 Hz, linearly interpolated; only
poses inside the GPS span) and aligned to it by Umeyama (1991) least squares, with a scale
(Sim(3)) and without (SE(3)). Printed per run: poses, poses matched, time span, path
lengths, Sim(3) scale, ATE RMSE after Sim(3) and after SE(3), and, from `report.json`
when present, the tracker's frames posed and reprojection figures.

The GPS track is metre level (no ground truth): good for the trajectory's shape and
scale, not for centimetres. Needs only numpy; not a runtime dependency of shoal.

Usage:
    python3 benches/gopro_vs_gps.py --gps DATA/gopro_karma_rs_imu/karma_position_enu.csv \\
        --traj estimate=OUT_EST --traj nominal=OUT_NOM [--json FILE]
"""
import argparse
import json
import os
import sys

import numpy as np


def read_tum(path):
    rows = [
        [float(x) for x in line.split()]
        for line in open(path)
        if line.strip() and not line.startswith("#")
    ]
    a = np.array(rows, dtype=float).reshape(-1, 8)
    return a[:, 0], a[:, 1:4]


def read_gps(path):
    a = np.loadtxt(path, delimiter=",", comments="#")
    return a[:, 0], a[:, 2:5]


def umeyama(src, dst, with_scale):
    """R, t, s minimising |dst - (s R src + t)|^2 (Umeyama 1991, eq. 40-42)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2, 2] = -1
    r = u @ sgn @ vt
    var_s = (xs**2).sum() / len(src)
    s = (d * np.diag(sgn)).sum() / var_s if with_scale and var_s > 0 else 1.0
    t = mu_d - s * r @ mu_s
    return r, t, s


def path_length(p):
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def report_figures(run_dir):
    path = os.path.join(run_dir, "report.json")
    if not os.path.isfile(path):
        return {}
    rep = json.load(open(path))
    out = {}
    clients = rep.get("clients") or []
    if clients:
        c = clients[0]
        for k in ("frames_in", "frames_posed", "frames_lost", "keyframes", "mode", "reprojection"):
            if k in c:
                out[k] = c[k]
        for k, v in c.items():
            if "reproj" in k and k not in out:
                out[k] = v
    return out


def compare(name, src, gps_t, gps_p):
    run_dir = src if os.path.isdir(src) else None
    traj = os.path.join(src, "trajectory_c0.txt") if run_dir else src
    t, p = read_tum(traj)
    res = {"name": name, "poses": int(len(t))}
    if run_dir:
        res.update(report_figures(run_dir))
    inside = (t >= gps_t[0]) & (t <= gps_t[-1])
    t, p = t[inside], p[inside]
    res["matched"] = int(len(t))
    if len(t) < 3:
        res["error"] = "fewer than 3 poses inside the GPS span"
        return res
    g = np.stack([np.interp(t, gps_t, gps_p[:, k]) for k in range(3)], axis=1)
    res["span_s"] = [float(t[0]), float(t[-1])]
    res["path_m"] = path_length(p)
    res["gps_path_m"] = path_length(g)
    for label, with_scale in (("sim3", True), ("se3", False)):
        r, tr, s = umeyama(p, g, with_scale)
        e = g - (s * (r @ p.T).T + tr)
        res[f"ate_rmse_{label}_m"] = float(np.sqrt((e**2).sum(1).mean()))
        if with_scale:
            res["sim3_scale"] = float(s)
    res["gps_rms_about_mean_m"] = float(np.sqrt(((g - g.mean(0)) ** 2).sum(1).mean()))
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gps", required=True)
    ap.add_argument("--traj", action="append", required=True, metavar="NAME=PATH")
    ap.add_argument("--json")
    a = ap.parse_args()
    gps_t, gps_p = read_gps(a.gps)
    results = []
    for spec in a.traj:
        name, _, path = spec.partition("=")
        results.append(compare(name, path, gps_t, gps_p))
    keys = ["poses", "matched", "span_s", "path_m", "gps_path_m", "sim3_scale",
            "ate_rmse_sim3_m", "ate_rmse_se3_m", "gps_rms_about_mean_m"]
    for r in results:
        print(f"== {r['name']}")
        for k in keys + sorted(set(r) - set(keys) - {"name"}):
            if k in r:
                v = r[k]
                if isinstance(v, float):
                    v = f"{v:.3f}"
                elif isinstance(v, list):
                    v = ", ".join(f"{x:.3f}" if isinstance(x, float) else str(x) for x in v)
                print(f"  {k:24} {v}")
    if a.json:
        json.dump(results, open(a.json, "w"), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
