#!/usr/bin/env python3
"""Compare shoal's ORB extractor (slam_core::features) with OpenCV's ORB.

Timing: the same images, OpenCV single-threaded (`cv2.setNumThreads(1)`),
`cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8)`, median of --runs
`detectAndCompute` calls; ours through the `orb_timing` example (median of the same number
of `extract` calls, with per-stage medians). Both run in this one script, one after the
other, so they see the same machine load.

Matching quality on KITTI 06 frames 12 -> 13: brute-force Hamming matching with Lowe's ratio
0.8, then RANSAC (fundamental matrix, 1 px, and essential matrix with the KITTI04-12
intrinsics, 1 px); inlier ratio = inliers / matches. Rows:
  - OpenCV features + cv2 BFMatcher,
  - our features + the same cv2 BFMatcher (same matcher, only the features differ),
  - our features + our matcher (slam_core brute force, ratio 0.8, unique, rotation check).

Requires `python3 -m pip install opencv-python-headless numpy`. The data folder is
`../shared/data` beside the repository (or --data).

Usage:
    python3 benches/orb_opencv.py [--runs 100] [--data DIR] [--no-build]
"""
import argparse
import glob
import os
import re
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FX = FY = 707.0912
CX, CY = 601.8873, 183.1104


def our_binary(build):
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target"))
    exe = os.path.join(target, "release", "examples", "orb_timing")
    if build:
        subprocess.run(
            ["cargo", "build", "--release", "-p", "slam_core", "--example", "orb_timing"],
            cwd=ROOT,
            check=True,
        )
    if not os.path.exists(exe):
        sys.exit(f"{exe} not found (build it or drop --no-build)")
    return exe


def time_opencv(path, runs):
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8)
    for _ in range(5):
        orb.detectAndCompute(img, None)
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        kps, _ = orb.detectAndCompute(img, None)
        ts.append((time.perf_counter() - t) * 1e3)
    return float(np.median(ts)), float(np.min(ts)), len(kps)


def time_ours(exe, path, runs):
    out = subprocess.run(
        [exe, "--runs", str(runs), path], check=True, capture_output=True, text=True
    ).stdout
    m = re.search(
        r"(\d+) kps, median total ([\d.]+) ms, min ([\d.]+) ms \(median stages: pyramid ([\d.]+), "
        r"detect ([\d.]+), orient ([\d.]+), describe ([\d.]+)\)",
        out,
    )
    if not m:
        sys.exit(f"cannot parse orb_timing output: {out}")
    n, med, mn, pyr, det, ori, des = m.groups()
    return float(med), float(mn), int(n), (float(pyr), float(det), float(ori), float(des))


def load_dump(path):
    kps, descs = [], []
    with open(path) as f:
        for line in f:
            p = line.split()
            kps.append((float(p[0]), float(p[1]), int(p[2]), float(p[3])))
            descs.append(np.frombuffer(bytes.fromhex(p[6]), dtype=np.uint8))
    return np.array(kps, dtype=np.float64), np.array(descs, dtype=np.uint8)


def ratio_matches(d1, d2, ratio=0.8):
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    good = []
    for pair in bf.knnMatch(d1, d2, k=2):
        if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
            good.append((pair[0].queryIdx, pair[0].trainIdx))
    return good


def inlier_ratios(p1, p2):
    """(matches, F inlier ratio, E inlier ratio) with RANSAC at 1 px."""
    n = len(p1)
    if n < 8:
        return n, float("nan"), float("nan")
    cv2.setRNGSeed(0)
    _, mf = cv2.findFundamentalMat(p1, p2, cv2.FM_RANSAC, 1.0, 0.999)
    k = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    cv2.setRNGSeed(0)
    _, me = cv2.findEssentialMat(p1, p2, k, cv2.RANSAC, 0.999, 1.0)
    rf = float(mf.sum()) / n if mf is not None else float("nan")
    re_ = float(me.sum()) / n if me is not None else float("nan")
    return n, rf, re_


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--no-build", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    exe = our_binary(not args.no_build)

    euroc = sorted(glob.glob(os.path.join(args.data, "euroc_v101_static/mav0/cam0/data/*.png")))
    kitti = os.path.join(args.data, "kitti07/image_0/000000.png")
    images = [("EuRoC 752x480", euroc[0] if euroc else None), ("KITTI 1226x370", kitti)]

    print(f"OpenCV {cv2.__version__}, 1 thread; {args.runs} runs per image; ms per frame")
    print(f"{'image':<16} {'ours med':>9} {'ours min':>9} {'cv med':>8} {'cv min':>8} "
          f"{'ours/cv':>8}   ours stages: pyramid/detect/orient/describe (median)")
    for name, path in images:
        if not path or not os.path.exists(path):
            print(f"{name:<16} image not found, skipped")
            continue
        om, omin, on, st = time_ours(exe, path, args.runs)
        cm, cmin, cn = time_opencv(path, args.runs)
        print(f"{name:<16} {om:9.3f} {omin:9.3f} {cm:8.3f} {cmin:8.3f} {om / cm:8.2f}   "
              f"{st[0]:.3f}/{st[1]:.3f}/{st[2]:.3f}/{st[3]:.3f}  ({on} vs {cn} kps)")

    a = os.path.join(args.data, "kitti06_frames/kitti06-12.png")
    b = os.path.join(args.data, "kitti06_frames/kitti06-13.png")
    if not (os.path.exists(a) and os.path.exists(b)):
        print("kitti06 frames not found, matching skipped")
        return
    rows = []
    orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8)
    ka, da = orb.detectAndCompute(cv2.imread(a, cv2.IMREAD_GRAYSCALE), None)
    kb, db = orb.detectAndCompute(cv2.imread(b, cv2.IMREAD_GRAYSCALE), None)
    m = ratio_matches(da, db)
    p1 = np.float64([ka[i].pt for i, _ in m])
    p2 = np.float64([kb[j].pt for _, j in m])
    rows.append(("OpenCV ORB + cv2 BF ratio 0.8", len(ka), len(kb)) + inlier_ratios(p1, p2))

    with tempfile.TemporaryDirectory() as tmp:
        fa, fb, fm = (os.path.join(tmp, n) for n in ("a.txt", "b.txt", "m.txt"))
        for img, out in ((a, fa), (b, fb)):
            subprocess.run([exe, "--dump", img, out], check=True, capture_output=True)
        (kpa, dsa), (kpb, dsb) = load_dump(fa), load_dump(fb)
        m = ratio_matches(dsa, dsb)
        p1 = np.float64([kpa[i, :2] for i, _ in m])
        p2 = np.float64([kpb[j, :2] for _, j in m])
        rows.append(("ours + cv2 BF ratio 0.8", len(kpa), len(kpb)) + inlier_ratios(p1, p2))

        subprocess.run([exe, "--match", a, b, fm], check=True, capture_output=True)
        mm = np.loadtxt(fm, ndmin=2)
        rows.append(
            ("ours + ours (ratio 0.8, rot. check)", len(kpa), len(kpb))
            + inlier_ratios(mm[:, 0:2].copy(), mm[:, 2:4].copy())
        )

    print("\nKITTI 06 frames 12 -> 13, RANSAC 1 px (inlier ratio = inliers / matches)")
    print(f"{'features + matcher':<38} {'kps':>10} {'matches':>8} {'F inl.':>7} {'E inl.':>7}")
    for name, na, nb, n, rf, re_ in rows:
        print(f"{name:<38} {f'{na}/{nb}':>10} {n:8d} {rf:7.3f} {re_:7.3f}")


if __name__ == "__main__":
    main()
