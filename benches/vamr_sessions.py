#!/usr/bin/env python3
"""Server keyframes of several sessions of an index-timed dataset (e.g. `vamr_checkerboard`)
judged in one frame: one Sim(3) alignment (Umeyama) of all sessions' keyframe positions to the
ground truth, and one fitted on the first session only (the others' errors are then those of
where the merge put them in the first session's frame).

usage: python3 benches/vamr_sessions.py GT_TUM FPS RANGES OUT/keyframes_server_c0.txt [...]
  GT_TUM: ground truth with the 0-based frame index as time; FPS: the run's --fps;
  RANGES: the sessions' --frames, e.g. 0:300,450:736 (for the path length).
"""
import sys

import numpy as np


def umeyama(est, ref):
    mu_e, mu_r = est.mean(0), ref.mean(0)
    e, r = est - mu_e, ref - mu_r
    u, d, vt = np.linalg.svd(r.T @ e / len(est))
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    scale = np.trace(np.diag(d) @ s) / (e ** 2).sum(1).mean()
    return lambda p: scale * (rot @ (p - mu_e).T).T + mu_r, scale


def main():
    gt = np.loadtxt(sys.argv[1])
    fps = float(sys.argv[2])
    ranges = [tuple(int(x) for x in r.split(":")) for r in sys.argv[3].split(",")]
    pos = {int(round(r[0])): r[1:4] for r in gt}
    sessions = []
    for f in sys.argv[4:]:
        rows = np.loadtxt(f, comments="#", ndmin=2)
        ks = [int(round(r[0] * fps)) for r in rows]
        sessions.append([(k, r[1:4]) for k, r in zip(ks, rows) if k in pos])
    length = sum(
        np.linalg.norm(np.diff(np.array([pos[k] for k in range(a, b) if k in pos]), axis=0), axis=1).sum()
        for a, b in ranges
    )
    every = [e for s in sessions for e in s]
    est = np.array([p for _, p in every])
    ref = np.array([pos[k] for k, _ in every])
    f, scale = umeyama(est, ref)
    err = np.linalg.norm(f(est) - ref, axis=1)
    rmse = np.sqrt((err ** 2).mean())
    print(f"all sessions, one Sim(3): ATE {rmse:.4f} m = {100 * rmse / length:.3f}% of {length:.2f} m "
          f"({len(every)} keyframes, scale {scale:.4f})")
    first = sessions[0]
    f0, _ = umeyama(np.array([p for _, p in first]), np.array([pos[k] for k, _ in first]))
    for i, s in enumerate(sessions):
        errs = " ".join(f"{k}:{1000 * np.linalg.norm(f0(p[None])[0] - pos[k]):.1f}" for k, p in s)
        print(f"session {i} in session 0's fitted frame, per keyframe (frame:error mm): {errs}")


if __name__ == "__main__":
    main()
