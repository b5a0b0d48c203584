"""How well can an IMU fix the metric scale of a path at all? An optimistic Cramer-Rao
lower bound on the 1-sigma relative error of the scale, for camera paths known exactly up
to scale (ground-truth files, TUM layout), and what it means for an SE(3) ATE target.

    python3 benches/scale_bound.py two-agents/agent0/groundtruth_cam0.txt \
        two-agents/agent1/groundtruth_cam0.txt [--target-percent 0.1]

(numpy; a side check, not a runtime part.) Several files share one scale (one map).

Model per agent: a_m(t) = R(t)^T (s * acc_vis(t) - g(theta)) + b(t) + n(t), with
n white (density sigma_a), b a random walk (density sigma_bw) represented by knots every
KNOT_S seconds (a restriction of the random walk: makes the bound optimistic), gravity
direction theta (2 DoF) free, b(0) with a weak prior. Poses exact (optimistic), gyro
exact (optimistic). Information on s after marginalising b and theta. Noise figures are
shoal's `ImuNoise::default()` (EuRoC's ADIS16448), what the synthetic scenarios use.

A scale error e leaves an SE(3)-aligned trajectory with an ATE of about |e| times the RMS
distance of its positions from their centroid (a rigid alignment cannot undo a scale), so
the script also gives the 1-sigma ATE and the chance that an unbiased estimator at the
bound meets an ATE target given as a percentage of the distance travelled.
"""
import math
import sys
import numpy as np

SIGMA_A = 2.0e-3      # m/s^2/sqrt(Hz), EuRoC accel noise density (shoal ImuNoise default)
SIGMA_BW = 3.0e-3     # m/s^3/sqrt(Hz), accel bias random walk
KNOT_S = 0.5
G = 9.81

def quat_to_rot(q):  # x y z w
    x, y, z, w = q
    return np.array([[1-2*(y*y+z*z), 2*(x*y-z*w), 2*(x*z+y*w)],
                     [2*(x*y+z*w), 1-2*(x*x+z*z), 2*(y*z-x*w)],
                     [2*(x*z-y*w), 2*(y*z+x*w), 1-2*(x*x+y*y)]])

def load(path):
    return np.loadtxt(path)


def info(path, sigma_a=SIGMA_A, sigma_bw=SIGMA_BW):
    d = load(path)
    t, p, q = d[:, 0], d[:, 1:4], d[:, 4:8]
    dt = np.median(np.diff(t))
    acc = np.zeros_like(p)
    acc[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2
    keep = slice(1, len(t) - 1)
    t, acc, q = t[keep], acc[keep], q[keep]
    n = len(t)
    knots = int(np.ceil((t[-1] - t[0]) / KNOT_S)) + 1
    nb = 3 * knots
    cols = 1 + 2 + nb
    sig = sigma_a / np.sqrt(dt)           # per sample of a dt-long average
    rows = []
    for k in range(n):
        R = quat_to_rot(q[k])
        H = np.zeros((3, cols))
        H[:, 0] = R.T @ acc[k] / sig
        gw = np.array([0.0, 0.0, -G])
        # d(-R^T g)/dtheta for g = Exp([tx, ty, 0]) g0: -R^T (-[g]x) e_i
        gx = np.array([[0, -gw[2], gw[1]], [gw[2], 0, -gw[0]], [-gw[1], gw[0], 0]])
        H[:, 1:3] = (R.T @ gx)[:, :2] / sig
        u = (t[k] - t[0]) / KNOT_S
        j = min(int(u), knots - 2)
        f = u - j
        H[:, 3 + 3*j:6 + 3*j] += (1 - f) * np.eye(3) / sig
        H[:, 3 + 3*(j+1):6 + 3*(j+1)] += f * np.eye(3) / sig
        rows.append(H)
    for j in range(knots - 1):
        H = np.zeros((3, cols))
        s = sigma_bw * np.sqrt(KNOT_S)
        H[:, 3 + 3*j:6 + 3*j] = -np.eye(3) / s
        H[:, 3 + 3*(j+1):6 + 3*(j+1)] = np.eye(3) / s
        rows.append(H)
    H = np.zeros((3, cols)); H[:, 3:6] = np.eye(3) / 0.2; rows.append(H)
    A = np.vstack(rows)
    J = A.T @ A
    # Schur complement onto s
    Jss = J[0, 0] - J[0, 1:] @ np.linalg.solve(J[1:, 1:], J[1:, 0])
    return Jss, np.sqrt(1.0 / J[0, 0])

def main(argv):
    target = 0.1
    if "--target-percent" in argv:
        i = argv.index("--target-percent")
        target = float(argv[i + 1])
        argv = argv[:i] + argv[i + 2:]
    total, positions, length = 0.0, [], 0.0
    for path in argv:
        Jss, naive = info(path)
        total += Jss
        p = load(path)[:, 1:4]
        positions.append(p)
        length += np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        print(f"{path}: scale 1-sigma >= {100 / np.sqrt(Jss):.3f}% "
              f"(with bias and gravity known: {100 * naive:.4f}%)")
    sigma = 1.0 / np.sqrt(total)
    p = np.vstack(positions)
    radius = np.sqrt(((p - p.mean(axis=0)) ** 2).sum(axis=1).mean())
    ate = sigma * radius
    z = target / 100 * length / ate
    print(f"joint: scale 1-sigma >= {100 * sigma:.3f}%; RMS radius {radius:.2f} m, "
          f"distance {length:.1f} m: SE(3) ATE 1-sigma >= {ate:.4f} m = "
          f"{100 * ate / length:.3f}% of the distance; "
          f"P(ATE <= {target}%) <= {100 * math.erf(z / math.sqrt(2)):.0f}%")


if __name__ == "__main__":
    main(sys.argv[1:])
