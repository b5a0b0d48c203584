#!/usr/bin/env python3
"""Offline calibration diagnostic on the EuRoC imu_april AprilGrid detections.

Question: when the AprilGrid corners are treated as natural features with UNKNOWN 3-D
positions (as our online MSCKF calibration does), what intrinsics do these detections
support? Is fx/fy ~ 461 (our filter) supported by the data, or is it a filter bias?

Model: pinhole + OpenCV radtan4 (k1 k2 p1 p2) applied to normalised coordinates,
u = fx*xd + cx, v = fy*yd + cy, pixel coordinates as given in the csv (0-based, pixel
centres at integers: yac's default detector is Kaess AprilTags + cv::cornerSubPix).

Solver: Levenberg-Marquardt with an analytic Jacobian and the pose blocks eliminated by a
Schur complement, Huber loss (1 px, per coordinate, IRLS weights). scipy's
least_squares(method='trf', x_scale='jac', loss='huber', jac_sparsity=...) is run as a
cross-check, restarted from the LM optimum (it must not lower the cost): started from
scratch, its lsmr trust-region steps had not converged after 100-200 evaluations
(target-based cost 4427 / 4379 / 4234 vs 4233.5 at the LM optimum, cx still moving).
1-sigma from (J^T W J)^-1 * s^2, s^2 = 2*cost/(m-n).

Runs:
  1. target-based: known target points, poses + 8 intrinsics free (also from the poor
     start, and re-fit with observations whose 2-D error > 1 px removed);
  2. self-calibration BA: 144 corner points free (init = target coords, or perturbed by
     1 cm), poses free, 8 intrinsics free; gauge = first pose fixed + distance between
     two far-apart corners held by a stiff prior;
  3. the same BA from the poor start [468, 447, 377, 240], zero distortion;
  4. focal profile: fx, fy both shifted by d = -7..+4 px from the BA optimum, rest free
     (self-cal BA, and the target-based fit at the same fx, fy for contrast);
  5. intrinsics fixed at config.yaml / at our filter's values: poses (+ points) only.
  Extras: all frames, and first / second half of the recording.

Requires `python3 -m pip install numpy scipy opencv-python-headless`.

Usage:
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
        python3 benches/april_selfcal.py [--step 5] [--no-extras] [--data DIR]
"""
import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import glob
import re
import sys
import time

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

try:
    import cv2

    cv2.setNumThreads(1)
except ImportError:  # homography fallback below
    cv2 = None

NAMES = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"]
FILT = np.array([461.22, 461.44, 365.22, 247.86, -0.295, 0.080, 0.0, 0.0])
POOR = np.array([468.0, 447.0, 377.0, 240.0, 0.0, 0.0, 0.0, 0.0])
F_SCALE = 1.0  # Huber threshold [px]
T0 = time.time()


def log(msg):
    print(msg, flush=True)


# ----------------------------------------------------------------------------- data
def load_config(path):
    txt = open(path).read()
    pp = re.search(r"proj_params:\s*\[([^\]]*)\]", txt).group(1)
    dp = re.search(r"dist_params:\s*\[([^\]]*)\]", txt).group(1)
    return np.array([float(v) for v in pp.split(",")] + [float(v) for v in dp.split(",")])


def load_frames(cam_dir):
    frames = []
    for f in sorted(glob.glob(os.path.join(cam_dir, "*.csv"))):
        ts = int(os.path.basename(f)[:-4])
        rows = [l for l in open(f).read().splitlines()[1:] if l.strip()]
        if not rows:
            frames.append((ts, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 3))))
            continue
        a = np.array([[float(v) for v in r.split(",")] for r in rows])
        kp = a[:, 5:7]
        p = a[:, 7:10]
        pid = (a[:, 10].astype(int) * 4 + a[:, 11].astype(int))
        frames.append((ts, kp, pid, p))
    return frames


def target_points(frames):
    tgt = np.full((144, 3), np.nan)
    for _, _, pid, p in frames:
        tgt[pid] = p
    return tgt


# ----------------------------------------------------------------------------- model
def rodrigues(r):
    th2 = np.sum(r * r, axis=1)
    th = np.sqrt(th2)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / (ths * ths))
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    return np.eye(3)[None] + A[:, None, None] * K + B[:, None, None] * (K @ K)


def project(intr, Xc):
    fx, fy, cx, cy, k1, k2, p1, p2 = intr
    x = Xc[:, 0] / Xc[:, 2]
    y = Xc[:, 1] / Xc[:, 2]
    r2 = x * x + y * y
    rad = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def pnp_pose(intr, obj, img):
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    d = np.asarray(intr[4:8], float)
    if cv2 is not None:
        ok, rv, tv = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rv, tv = cv2.solvePnP(obj, img, K, d)
        ok, rv, tv = cv2.solvePnP(obj, img, K, d, rv, tv, True, cv2.SOLVEPNP_ITERATIVE)
        return np.concatenate([rv.ravel(), tv.ravel()])
    raise RuntimeError("opencv-python-headless is needed for the pose init")


# ----------------------------------------------------------------------------- problem
def skew(v):
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return K


def rvec_of(R):
    return np.array([cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel() for r in R])


class BA:
    """Reprojection problem over intrinsics (8), corner points (144x3) and poses (F x SE3).

    State = (intr, pts, R, t) with X_c = R X + t.  Full tangent vector layout:
    [8 intrinsics | 3*144 points | 6*F poses (dtheta, dt); R <- exp(dtheta) R, t <- t + dt].
    Fixed entries (fixed intrinsics, fixed / unobserved points, pose 0) are removed.
    Solved by Levenberg-Marquardt on the Huber cost (IRLS weights, per coordinate as in
    scipy's loss='huber') with the pose blocks eliminated by a Schur complement.
    """

    def __init__(self, frames, intr, pts, R, t, fix_intr=(), fix_points=False,
                 fix_pose0=False, scale_pair=None):
        self.F, self.P = len(frames), 144
        self.fi = np.concatenate([np.full(len(f[2]), k) for k, f in enumerate(frames)])
        self.pi = np.concatenate([f[2] for f in frames])
        self.uv = np.concatenate([f[1] for f in frames])
        self.N = len(self.fi)
        self.oP, self.oT = 8, 8 + 3 * self.P
        self.n = self.oT + 6 * self.F
        free = np.ones(self.n, bool)
        free[list(fix_intr)] = False
        self.seen = np.zeros(self.P, bool)
        self.seen[self.pi] = True
        for p in range(self.P):
            if fix_points or not self.seen[p]:
                free[self.oP + 3 * p:self.oP + 3 * p + 3] = False
        if fix_pose0:
            free[self.oT:self.oT + 6] = False
        self.free = free
        self.fidx = np.flatnonzero(free)
        self.col = np.full(self.n, -1)
        self.col[self.fidx] = np.arange(len(self.fidx))
        self.scale_pair = scale_pair  # (a, b, distance [m], weight [px/m])
        self.m = 2 * self.N + (scale_pair is not None)
        self.st = (np.array(intr, float), np.array(pts, float), np.array(R, float), np.array(t, float))
        self.nfree = len(self.fidx)
        self.nb = int(np.sum(self.fidx >= self.oT))
        self.na = self.nfree - self.nb

    # --- model
    def residual(self, st):
        intr, pts, R, t = st
        Xc = np.einsum("nij,nj->ni", R[self.fi], pts[self.pi]) + t[self.fi]
        r = (project(intr, Xc) - self.uv).ravel()
        if self.scale_pair is not None:
            a, b, d, w = self.scale_pair
            r = np.r_[r, w * (np.linalg.norm(pts[a] - pts[b]) - d)]
        return r

    def linearize(self, st):
        intr, pts, R, t = st
        fx, fy, cx, cy, k1, k2, p1, p2 = intr
        Rn = R[self.fi]
        RX = np.einsum("nij,nj->ni", Rn, pts[self.pi])
        Xc = RX + t[self.fi]
        iz = 1.0 / Xc[:, 2]
        x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 * r2
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        res = np.stack([fx * xd + cx - self.uv[:, 0], fy * yd + cy - self.uv[:, 1]], 1).ravel()
        g = k1 + 2 * k2 * r2
        D = np.empty((self.N, 2, 2))
        D[:, 0, 0] = rad + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x
        D[:, 0, 1] = 2 * x * y * g + 2 * p1 * x + 2 * p2 * y
        D[:, 1, 0] = D[:, 0, 1]
        D[:, 1, 1] = rad + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x
        D[:, 0, :] *= fx
        D[:, 1, :] *= fy
        A = np.zeros((self.N, 2, 3))
        A[:, 0, 0] = iz
        A[:, 1, 1] = iz
        A[:, 0, 2] = -x * iz
        A[:, 1, 2] = -y * iz
        dXc = D @ A  # (N,2,3)
        Ji = np.zeros((self.N, 2, 8))
        Ji[:, 0, 0], Ji[:, 0, 2] = xd, 1
        Ji[:, 1, 1], Ji[:, 1, 3] = yd, 1
        Ji[:, 0, 4], Ji[:, 0, 5] = fx * x * r2, fx * x * r2 * r2
        Ji[:, 1, 4], Ji[:, 1, 5] = fy * y * r2, fy * y * r2 * r2
        Ji[:, 0, 6], Ji[:, 0, 7] = fx * 2 * x * y, fx * (r2 + 2 * x * x)
        Ji[:, 1, 6], Ji[:, 1, 7] = fy * (r2 + 2 * y * y), fy * 2 * x * y
        Jp = dXc @ Rn
        Jr = -dXc @ skew(RX)
        vals = np.concatenate([Ji, Jp, Jr, dXc], axis=2)  # (N,2,17)
        cols = np.concatenate([np.broadcast_to(np.arange(8), (self.N, 8)),
                               self.oP + 3 * self.pi[:, None] + np.arange(3),
                               self.oT + 6 * self.fi[:, None] + np.arange(6)], axis=1)
        cols = np.broadcast_to(cols[:, None, :], (self.N, 2, 17))
        rows = np.broadcast_to(np.arange(2 * self.N).reshape(self.N, 2, 1), (self.N, 2, 17))
        rows, cols, vals = rows.ravel(), cols.ravel(), vals.ravel()
        if self.scale_pair is not None:
            a, b, d, w = self.scale_pair
            dv = pts[a] - pts[b]
            L = np.linalg.norm(dv)
            res = np.r_[res, w * (L - d)]
            rows = np.r_[rows, np.full(6, 2 * self.N)]
            cols = np.r_[cols, self.oP + 3 * a + np.arange(3), self.oP + 3 * b + np.arange(3)]
            vals = np.r_[vals, w * dv / L, -w * dv / L]
        c = self.col[cols]
        keep = c >= 0
        J = sp.csr_matrix((vals[keep], (rows[keep], c[keep])), shape=(self.m, self.nfree))
        return res, J

    def weights(self, r):
        a = np.abs(r)
        w = np.where(a <= F_SCALE, 1.0, F_SCALE / np.maximum(a, 1e-300))
        if self.scale_pair is not None:
            w[-1] = 1.0
        return w

    def cost(self, r):
        rr = r[: 2 * self.N]
        z = (rr / F_SCALE) ** 2
        c = 0.5 * F_SCALE ** 2 * np.sum(np.where(z <= 1, z, 2 * np.sqrt(z) - 1))
        if self.scale_pair is not None:
            c += 0.5 * r[-1] ** 2
        return c

    def retract(self, st, dx):
        intr, pts, R, t = st
        full = np.zeros(self.n)
        full[self.fidx] = dx
        intr = intr + full[:8]
        pts = pts + full[self.oP:self.oT].reshape(-1, 3)
        d = full[self.oT:].reshape(-1, 6)
        if cv2 is not None:
            dR = np.array([cv2.Rodrigues(v)[0] for v in d[:, :3]])
        else:
            dR = rodrigues(d[:, :3])
        return intr, pts, dR @ R, t + d[:, 3:]

    # --- linear algebra
    def _normal(self, J, w):
        Jw = sp.diags(np.sqrt(w)) @ J
        H = (Jw.T @ Jw).tocsc()
        return H, Jw

    def _split(self, H):
        na = self.na
        Haa = H[:na, :na].toarray()
        Hab = H[:na, na:].tocsr()
        Hbb = H[na:, na:].tocoo()
        blocks = np.zeros((self.nb // 6, 6, 6))
        on = Hbb.row // 6 == Hbb.col // 6
        blocks[Hbb.row[on] // 6, Hbb.row[on] % 6, Hbb.col[on] % 6] = Hbb.data[on]
        return Haa, Hab, blocks

    def _schur(self, Haa, Hab, blocks):
        """Return S = Haa - Hab Hbb^-1 Hba and a function applying Hbb^-1 (blocks 6x6)."""
        inv = np.linalg.inv(blocks)
        Hd = Hab.toarray().reshape(self.na, self.nb // 6, 6)
        HB = np.einsum("akj,kji->aki", Hd, inv).reshape(self.na, self.nb)
        S = Haa - HB @ Hd.reshape(self.na, self.nb).T

        def binv(v):
            return np.einsum("kij,kj->ki", inv, v.reshape(-1, 6)).ravel()

        return S, HB, Hd.reshape(self.na, self.nb), binv

    def _solve(self, H, g, lam):
        Haa, Hab, blocks = self._split(H)
        Haa = Haa + lam * np.diag(np.diag(Haa) + 1e-12)
        idx = np.arange(6)
        blocks = blocks.copy()
        blocks[:, idx, idx] *= 1 + lam
        blocks[:, idx, idx] += 1e-12
        S, HB, Hd, binv = self._schur(Haa, Hab, blocks)
        ga, gb = g[: self.na], g[self.na:]
        da = np.linalg.solve(S, -ga + HB @ gb)
        db = binv(-gb - Hd.T @ da)
        return np.r_[da, db]

    def solve(self, max_iter=100, rtol=1e-11):
        st = self.st
        r, J = self.linearize(st)
        c = self.cost(r)
        lam = 1e-4
        it = 0
        for it in range(1, max_iter + 1):
            w = self.weights(r)
            H, Jw = self._normal(J, w)
            g = J.T @ (w * r)
            improved = False
            for _ in range(12):
                dx = self._solve(H, g, lam)
                st_new = self.retract(st, dx)
                r_new = self.residual(st_new)
                c_new = self.cost(r_new)
                if c_new < c:
                    improved = True
                    break
                lam *= 4
            if not improved:
                break
            dc = c - c_new
            st, c = st_new, c_new
            r, J = self.linearize(st)
            lam = max(lam / 3, 1e-9)
            if dc < rtol * c:
                break
        self.st, self.iters, self._cost = st, it, c
        return self

    def stats(self, st=None):
        st = self.st if st is None else st
        r = self.residual(st)
        rr = r[: 2 * self.N]
        e = np.hypot(rr[0::2], rr[1::2])
        return dict(rms=np.sqrt(np.mean(rr * rr)), rms2d=np.sqrt(np.mean(e * e)), cost=self.cost(r),
                    n_out=int(np.sum(e > 1.0)), nobs=self.N)

    def intr_cov(self):
        """(J^T W J)^-1 s^2 for the free intrinsics (Schur complement on the pose blocks)."""
        r, J = self.linearize(self.st)
        H, _ = self._normal(J, self.weights(r))
        Haa, Hab, blocks = self._split(H)
        S = self._schur(Haa, Hab, blocks)[0]
        ni = int(np.sum(self.fidx < 8))
        # only the intrinsics block of S^-1 is needed
        C = np.linalg.inv(S)[:ni, :ni]
        s2 = 2 * self.cost(r) / (self.m - self.nfree)
        names = [NAMES[i] for i in self.fidx[self.fidx < 8]]
        return names, C * s2, s2

    # --- scipy cross-check: least_squares(trf, jac_sparsity, x_scale='jac') from this state
    def scipy_check(self, max_nfev=30):
        intr, pts, R, t = self.st
        rv = rvec_of(R)
        full0 = np.concatenate([intr, pts.ravel(), np.c_[rv, t].ravel()])

        def unpack(x):
            f = full0.copy()
            f[self.fidx] = x
            return (f[:8], f[self.oP:self.oT].reshape(-1, 3),
                    rodrigues(f[self.oT:].reshape(-1, 6)[:, :3]), f[self.oT:].reshape(-1, 6)[:, 3:])

        def fun(x):
            return self.residual(unpack(x))

        _, J = self.linearize(self.st)
        S = J.copy()
        S.data[:] = 1
        x0 = full0[self.fidx]
        res = least_squares(fun, x0, jac_sparsity=S, method="trf", x_scale="jac", loss="huber",
                            f_scale=F_SCALE, max_nfev=max_nfev, tr_solver="lsmr",
                            ftol=1e-12, xtol=1e-12, gtol=1e-12)
        st2 = unpack(res.x)
        return self.cost(fun(x0)), self.cost(fun(res.x)), st2[0] - intr, res.nfev


# ----------------------------------------------------------------------------- helpers
def init_poses(frames, intr, tgt):
    P = np.array([pnp_pose(intr, tgt[pid].astype(np.float64), kp.astype(np.float64))
                  for _, kp, pid, _ in frames])
    return rodrigues(P[:, :3]), P[:, 3:].copy()


def scale_pair(tgt):
    a, b = 0, 35 * 4 + 2  # tag 0 corner 0 and tag 35 corner 2 (opposite grid corners)
    return (a, b, float(np.linalg.norm(tgt[a] - tgt[b])), 1e4)


def umeyama(src, dst):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s, d = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(d.T @ s / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    c = np.trace(np.diag(S) @ D) / np.mean(np.sum(s * s, 1))
    return c, R, mu_d - c * R @ mu_s


def point_geometry(pts, tgt, mask):
    c, R, t = umeyama(pts[mask], tgt[mask])
    al = (c * (R @ pts[mask].T)).T + t
    dev = al - tgt[mask]
    err = np.linalg.norm(dev, axis=1) * 1e3
    q = al - al.mean(0)
    nrm = np.linalg.svd(q)[2][2]
    off = (q @ nrm) * 1e3
    # dome: out-of-plane deviation (target z) fitted by a + b*rho^2 around the grid centre
    cxy = tgt[mask][:, :2] - tgt[mask][:, :2].mean(0)
    rho2 = np.sum(cxy * cxy, 1)
    co = np.linalg.lstsq(np.c_[np.ones_like(rho2), rho2], dev[:, 2] * 1e3, rcond=None)[0]
    aff = np.linalg.lstsq(np.c_[tgt[mask][:, :2], np.ones(mask.sum())], al[:, :2], rcond=None)[0]
    return dict(rms_mm=np.sqrt(np.mean(err ** 2)), max_mm=err.max(),
                plane_rms_mm=np.sqrt(np.mean(off ** 2)), plane_max_mm=np.abs(off).max(),
                dome_mm=co[1] * np.max(rho2), sx=aff[0, 0], sy=aff[1, 1])


def f8(v, w=8):
    return " ".join((f"{x:{w}.3f}" if i < 4 else f"{x:{w + 1}.5f}") for i, x in enumerate(v))


HDR = "    " + " ".join(f"{n:>8s}" if i < 4 else f"{n:>9s}" for i, n in enumerate(NAMES))


def run(frames, tgt, intr0, mode, pts0=None, pose_intr=None, fix_intr=(), warm=None,
        max_iter=100):
    """mode 'target': known target points; 'self': points free (gauge: pose 0 + scale prior)."""
    R, t = init_poses(frames, intr0 if pose_intr is None else pose_intr, tgt)
    pts = tgt.copy() if pts0 is None else pts0
    if warm is not None:
        intr0, pts, R, t = warm
    if mode == "target":
        ba = BA(frames, intr0, pts, R, t, fix_intr=fix_intr, fix_points=True)
    else:
        ba = BA(frames, intr0, pts, R, t, fix_intr=fix_intr, fix_pose0=True, scale_pair=scale_pair(tgt))
    t0 = time.time()
    ba.solve(max_iter=max_iter)
    ba.secs = time.time() - t0
    return ba


def report(label, ba, ref, tgt=None, sigma=True):
    intr = ba.st[0]
    st = ba.stats()
    log(f"  {label}: {ba.F} frames, {ba.N} obs, {ba.iters} it, {ba.secs:.1f}s; rms {st['rms']:.4f} px/coord"
        f" (2-D {st['rms2d']:.4f}), cost {st['cost']:.2f}, 2-D err > 1px: {st['n_out']}")
    log("    est : " + f8(intr))
    out = (intr, None, None, None)
    if sigma:
        names, C, s2 = ba.intr_cov()
        sd = dict(zip(names, np.sqrt(np.diag(C))))
        log("    1sig: " + " ".join(((f"{sd[n]:8.3f}" if i < 4 else f"{sd[n]:9.5f}") if n in sd else
                                     ("   fixed" if i < 4 else "    fixed")) for i, n in enumerate(NAMES))
            + f"   (s = {np.sqrt(s2):.4f} px)")
        out = (intr, names, C, s2)
    log("    -ref: " + f8(intr - ref) + "   (est - config.yaml)")
    if tgt is not None and not np.all(~ba.free[ba.oP:ba.oT]):
        g = point_geometry(ba.st[1], tgt, ba.seen)
        log(f"    pts : vs target after similarity: rms {g['rms_mm']:.2f} mm, max {g['max_mm']:.2f} mm;"
            f" off best plane rms {g['plane_rms_mm']:.2f} max {g['plane_max_mm']:.2f} mm;"
            f" bow z(corner)-z(centre) {g['dome_mm']:+.2f} mm; in-plane scale x {g['sx']:.4f} y {g['sy']:.4f}")
    return out


def trim(frames, ba, thr):
    r = ba.residual(ba.st)[: 2 * ba.N]
    e = np.hypot(r[0::2], r[1::2])
    out, k0 = [], 0
    for f in frames:
        n = len(f[2])
        m = e[k0:k0 + n] <= thr
        k0 += n
        out.append((f[0], f[1][m], f[2][m], f[3][m]))
    return out


def corr(C):
    d = np.sqrt(np.diag(C))
    return C / np.outer(d, d)


# ----------------------------------------------------------------------------- main
def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(here, "..", "..", "shared", "data", "euroc_imu_april"))
    ap.add_argument("--step", type=int, default=5, help="use frames with index %% STEP == 0 (default 5)")
    ap.add_argument("--min-corners", type=int, default=20)
    ap.add_argument("--no-extras", action="store_true", help="skip all-frames and half splits")
    args = ap.parse_args()
    np.set_printoptions(precision=3, suppress=True, linewidth=160)

    ref = load_config(os.path.join(args.data, "config.yaml"))
    frames_all = load_frames(os.path.join(args.data, "cam0"))
    tgt = target_points(frames_all)
    idx = [i for i, f in enumerate(frames_all) if len(f[2]) >= args.min_corners]
    good = [frames_all[i] for i in idx]
    sub = [frames_all[i] for i in idx if i % args.step == 0]
    allkp = np.concatenate([f[1] for f in good])
    log(f"data: {len(frames_all)} frames, {len(good)} with >= {args.min_corners} corners ({len(allkp)} corners);"
        f" subsample = frame index % {args.step} == 0 -> {len(sub)} frames, {sum(len(f[2]) for f in sub)} corners")
    f32 = np.all(np.round(allkp.astype(np.float32).astype(np.float64), 10) == allkp)
    frac = allkp - np.floor(allkp)
    hist = np.histogram(frac.ravel(), bins=10, range=(0, 1))[0]
    log(f"pixels: x [{allkp[:, 0].min():.2f}, {allkp[:, 0].max():.2f}], y [{allkp[:, 1].min():.2f},"
        f" {allkp[:, 1].max():.2f}] in 752x480; values are float32 (cv::Point2f): {f32};"
        f" fractional-part histogram (0.0..1.0, 10 bins, %): {np.round(100 * hist / hist.sum(), 1)}")
    log(f"config.yaml : {f8(ref)}")
    log(f"our filter  : {f8(FILT)}")
    log(HDR)
    log("solver: LM + Schur on poses, Huber 1 px per coordinate; cost = 0.5*sum rho(r^2) [px^2];"
        " rms = raw per-coordinate px")

    # 1 -------------------------------------------------------------------------
    log("\n[1] TARGET-BASED calibration (known target points; poses + 8 intrinsics free)")
    b1 = run(sub, tgt, ref, "target")
    i1, _, C1, s21 = report("init config.yaml", b1, ref)
    c0, c1, di, nf = b1.scipy_check()
    log(f"    scipy least_squares(trf, jac_sparsity, x_scale='jac', huber) restarted here: cost {c0:.3f} ->"
        f" {c1:.3f} in {nf} nfev, max |d intr| {np.abs(di).max():.2e}")
    b1p = run(sub, tgt, POOR, "target")
    report("init poor [468 447 377 240, 0 dist]", b1p, ref, sigma=False)
    b1t = run(trim(sub, b1, 1.0), tgt, ref, "target")
    report("trimmed: obs with 2-D error > 1 px at the optimum removed", b1t, ref)
    log("    corr(fx, fy, k1, k2) target-based:  " + np.array2string(corr(C1)[np.ix_([0, 1, 4, 5], [0, 1, 4, 5])]).replace("\n", ""))

    # 2 -------------------------------------------------------------------------
    log("\n[2] SELF-CALIBRATION BA (144 points free + poses + 8 intrinsics; gauge: pose 0 fixed and"
        " |P(tag0,c0) - P(tag35,c2)| = 0.9329 m by a stiff prior)")
    b2 = run(sub, tgt, ref, "self")
    i2, n2, C2, s22 = report("points init = target, intr init = config.yaml", b2, ref, tgt)
    c0, c1, di, nf = b2.scipy_check()
    log(f"    scipy least_squares(trf, jac_sparsity, x_scale='jac', huber) restarted here: cost {c0:.3f} ->"
        f" {c1:.3f} in {nf} nfev, max |d intr| {np.abs(di).max():.2e}")
    rng = np.random.default_rng(0)
    ptsp = tgt + rng.normal(0, 0.01, tgt.shape)
    ptsp[scale_pair(tgt)[1]] = tgt[scale_pair(tgt)[1]]
    ptsp[0] = tgt[0]
    b2p = run(sub, tgt, ref, "self", pts0=ptsp)
    report("points init = target + N(0, 1 cm) per axis, intr init = config.yaml", b2p, ref, tgt)
    b2t = run(trim(sub, b2, 1.0), tgt, ref, "self")
    report("trimmed: obs with 2-D error > 1 px at the optimum removed", b2t, ref, tgt)
    log("    correlation (self-cal, untrimmed):")
    log("        " + " ".join(f"{n:>6s}" for n in NAMES))
    for n, row in zip(NAMES, corr(C2)):
        log(f"      {n}" + " ".join(f"{v:6.3f}" for v in row))

    # 3 -------------------------------------------------------------------------
    log("\n[3] SELF-CALIBRATION BA from the POOR start [468 447 377 240], zero distortion"
        " (poses by PnP with the poor intrinsics)")
    b3 = run(sub, tgt, POOR, "self")
    report("points init = target", b3, ref, tgt, sigma=False)
    b3p = run(sub, tgt, POOR, "self", pts0=ptsp)
    report("points init = target + N(0, 1 cm)", b3p, ref, tgt, sigma=False)

    # 5 -------------------------------------------------------------------------
    log("\n[5] intrinsics + distortion FIXED; poses (+ points) optimised. dchi2 = 2*dcost/s^2 vs the free optimum"
        f" of the same model (s^2 target {s21:.4f}, self-cal {s22:.4f})")
    log(f"    {'intrinsics':<24s} {'model':<24s} {'rms px':>8s} {'cost':>10s} {'dcost':>9s} {'dchi2':>8s}")
    for mode, opt, s2, lab in [("target", b1, s21, "known target, poses"), ("self", b2, s22, "free points + poses")]:
        co = opt.stats()["cost"]
        for name, v in [("free optimum", None), ("config.yaml", ref), ("our filter", FILT),
                        ("self-cal optimum [2]" if mode == "target" else "target optimum [1]", i2 if mode == "target" else i1)]:
            if v is None:
                st = opt.stats()
            else:
                st = run(sub, tgt, v, mode, fix_intr=range(8)).stats()
            log(f"    {name:<24s} {lab:<24s} {st['rms']:8.4f} {st['cost']:10.2f} {st['cost'] - co:9.2f}"
                f" {2 * (st['cost'] - co) / s2:8.1f}")

    # 4 -------------------------------------------------------------------------
    log("\n[4] FOCAL PROFILE: fx = fx*+d, fy = fy*+d fixed (fx*, fy* = self-cal optimum [2]); cx cy k1 k2 p1 p2,"
        " poses (+ points) free. Self-cal and, for contrast, target-based at the same fx, fy")
    log(f"    {'d':>3s} {'fx':>8s} {'fy':>8s} | {'cx':>7s} {'cy':>7s} {'k1':>8s} {'k2':>8s} {'rms':>7s} {'dcost':>8s}"
        f" {'dchi2':>7s} | {'target: cx':>10s} {'k1':>8s} {'rms':>7s} {'dcost':>8s} {'dchi2':>7s}")
    cs, ct = b2.stats()["cost"], b1.stats()["cost"]
    for d in range(-7, 5):
        v = i2.copy()
        v[:2] += d
        ws = (v, b2.st[1], b2.st[2], b2.st[3])
        ps = run(sub, tgt, v, "self", fix_intr=(0, 1), warm=ws)
        wt = (np.r_[v[:2], b1.st[0][2:]], b1.st[1], b1.st[2], b1.st[3])
        pt = run(sub, tgt, v, "target", fix_intr=(0, 1), warm=wt)
        a, b = ps.stats(), pt.stats()
        iv, it_ = ps.st[0], pt.st[0]
        log(f"    {d:3d} {iv[0]:8.3f} {iv[1]:8.3f} | {iv[2]:7.2f} {iv[3]:7.2f} {iv[4]:8.5f} {iv[5]:8.5f} {a['rms']:7.4f}"
            f" {a['cost'] - cs:8.2f} {2 * (a['cost'] - cs) / s22:7.1f} | {it_[2]:10.2f} {it_[4]:8.5f} {b['rms']:7.4f}"
            f" {b['cost'] - ct:8.2f} {2 * (b['cost'] - ct) / s21:7.1f}")
    log(f"    ({time.time() - T0:.0f}s so far)")

    # extras ----------------------------------------------------------------------
    if not args.no_extras:
        log("\n[extras] all frames / halves (init config.yaml)")
        t_mid = frames_all[0][0] + 36e9
        h1 = [f for f in good if f[0] < t_mid]
        h2 = [f for f in good if f[0] >= t_mid]
        for lab, fr in [("ALL frames", good), ("1st half (< 36 s)", h1), ("2nd half (>= 36 s)", h2)]:
            report(f"{lab} target-based", run(fr, tgt, ref, "target"), ref)
            report(f"{lab} self-cal BA", run(fr, tgt, ref, "self"), ref, tgt)
            log(f"    ({time.time() - T0:.0f}s so far)")
    log(f"\ntotal time {time.time() - T0:.0f}s")


if __name__ == "__main__":
    main()
