"""Which camera-IMU rotation R_bc fits the phone clip (phone_honorv10)? Side check for the
phone loader's device-axis convention (issue 17): the camera's frame-to-frame rotations from
ORB matches + the essential matrix (OpenCV, test-side only) against the gyro integrated over
the same intervals, for every axis-aligned R_bc (24 candidates). Prints the mean angular
residual per candidate, best first.

    python3 benches/scripts/phone_axes.py ../shared/data/phone_honorv10
"""
import csv, itertools, sys
import cv2
import numpy as np

root = sys.argv[1]
meta = [r for r in csv.reader(open(f"{root}/movie_metadata.csv"))][1:]
t_frames = [int(r[0]) + int(r[6]) // 2 for r in meta]  # mid-row times
f = float(meta[0][1])
imu = np.array([[float(x) for x in r[:4]] for r in list(csv.reader(open(f"{root}/gyro_accel.csv")))[1:]])

def gyro_rot(t0, t1):
    R = np.eye(3)
    ts = imu[:, 0]
    for k in range(len(ts) - 1):
        a, b = max(ts[k], t0), min(ts[k + 1], t1)
        if b > a:
            w = imu[k, 1:4] * (b - a) * 1e-9
            R = R @ cv2.Rodrigues(w)[0]
    return R

imgs = [cv2.imread(f"{root}/frames/{k:04d}.png", cv2.IMREAD_GRAYSCALE) for k in range(1, len(meta) + 1)]
h, w = imgs[0].shape
K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
orb = cv2.ORB_create(2000)
bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
pairs = []
step = 3
for i in range(0, len(imgs) - step, step):
    j = i + step
    k1, d1 = orb.detectAndCompute(imgs[i], None)
    k2, d2 = orb.detectAndCompute(imgs[j], None)
    m = bf.match(d1, d2)
    p1 = np.float32([k1[x.queryIdx].pt for x in m]); p2 = np.float32([k2[x.trainIdx].pt for x in m])
    E, mask = cv2.findEssentialMat(p1, p2, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        continue
    _, R, t, _ = cv2.recoverPose(E, p1, p2, K, mask=mask)
    # R maps camera i to camera j coordinates: R_c,ij (camera j from i) -> rotation of camera i->j = R.T
    pairs.append((R.T, gyro_rot(t_frames[i], t_frames[j]), len(m)))

cands = []
for perm in itertools.permutations(range(3)):
    for signs in itertools.product([1, -1], repeat=3):
        M = np.zeros((3, 3))
        for r, (c, s) in enumerate(zip(perm, signs)):
            M[r, c] = s
        if np.linalg.det(M) < 0:
            continue
        errs = []
        for Rc, Rb, _ in pairs:
            E = Rb.T @ M @ Rc @ M.T  # R_bc R_c R_bc^T vs ΔR_b
            errs.append(np.degrees(np.linalg.norm(cv2.Rodrigues(E)[0])))
        cands.append((np.mean(errs), M))
cands.sort(key=lambda c: c[0])
print(f"{len(pairs)} frame pairs; gyro turn per pair {np.mean([np.degrees(np.linalg.norm(cv2.Rodrigues(p[1])[0])) for p in pairs]):.2f} deg")
for e, M in cands[:4]:
    print(f"mean residual {e:.3f} deg for R_bc rows {M.astype(int).tolist()}")
