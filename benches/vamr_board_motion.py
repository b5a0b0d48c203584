#!/usr/bin/env python3
"""Does the checkerboard of `vamr_checkerboard` move on the desk between the two passes?

The ground truth is the camera pose relative to the board. Where two frames have nearly the
same ground-truth pose (e.g. 22 and 522), a static scene looks the same in both: the board's
corners and the desk objects around it (keyboard, mouse) shift by the same few pixels. This
prints, per frame pair, the mean shift of the 9x6 board corners and the shift of templates of
the keyboard and the mouse (normalised cross-correlation). A desk object that shifts tens of
pixels more than the board means the board moved relative to the desk, so no static-world map
of the whole scene can agree with the board-relative ground truth across the two passes.

usage: python3 benches/vamr_board_motion.py [../shared/data/vamr_checkerboard]
needs: pip install opencv-python-headless numpy (side-by-side checks only)
"""
import sys

import cv2
import numpy as np

ROOT = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/vamr_checkerboard"
# Template boxes (y0, y1, x0, x1) in the first frame of each pair.
TEMPLATES = {"keyboard": (0, 50, 400, 660), "mouse": (120, 200, 640, 740)}
PAIRS = [(3, 516), (9, 522), (22, 522), (402, 609), (393, 609), (537, 729), (639, 699), (624, 714)]


def image(k):
    return cv2.imread(f"{ROOT}/images/img_{k + 1:04d}.jpg", cv2.IMREAD_GRAYSCALE)


def gt_pose(gt, k):
    r = gt[k]
    return r[1:4], r[4:8]


def main():
    gt = np.loadtxt(f"{ROOT}/groundtruth_tum.txt")
    print("pair       gt baseline  board shift px   keyboard shift px   mouse shift px")
    for a, b in PAIRS:
        ia, ib = image(a), image(b)
        ok_a, ca = cv2.findChessboardCorners(ia, (9, 6))
        ok_b, cb = cv2.findChessboardCorners(ib, (9, 6))
        board = (cb - ca).reshape(-1, 2).mean(0) if ok_a and ok_b else None
        base = np.linalg.norm(gt_pose(gt, a)[0] - gt_pose(gt, b)[0])
        shifts = {}
        for name, (y0, y1, x0, x1) in TEMPLATES.items():
            r = cv2.matchTemplate(ib, ia[y0:y1, x0:x1], cv2.TM_CCOEFF_NORMED)
            _, score, _, loc = cv2.minMaxLoc(r)
            shifts[name] = (loc[0] - x0, loc[1] - y0, score)
        fmt = lambda s: f"({s[0]:4d},{s[1]:4d}) ncc {s[2]:.2f}"
        board_txt = f"({board[0]:6.1f},{board[1]:6.1f})" if board is not None else "not found"
        print(f"{a:3d}->{b:3d}  {1000 * base:6.1f} mm  {board_txt:16s} "
              f"{fmt(shifts['keyboard'])}  {fmt(shifts['mouse'])}")


if __name__ == "__main__":
    main()
