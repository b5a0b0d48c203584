#!/usr/bin/env python3
"""Long-run memory benchmark (issue 6): resident memory of every shoal process over a run of
many minutes of data, beside the server map's size.

Two steps:

  long_run_rss.py palindrome SRC OUT FRAMES
      Builds a EuRoC-layout dataset of FRAMES frames from a `shoal sim` sequence SRC by
      replaying it forwards, backwards, forwards, ... (frame order 0..M-1, M-2..0, 1..M-1, ...)
      on a continuous 20 Hz clock: no pose jumps, no copied images (cam0/data is a symlink
      to SRC's images, data.csv names them). The IMU follows the same time map (gyro negated
      on backward stretches, accelerometer unchanged: both are what a camera moving the path
      backwards measures); ground truth likewise.

  long_run_rss.py run SHOAL DATASET OUT [--every S] [-- EXTRA shoal run ARGS...]
      Runs `SHOAL run --lockstep --dataset DATASET --out OUT ...` and samples, every S seconds
      (default 5), VmRSS of the launcher and each child (/proc/PID/status), and the mapper's
      map size and the tracker's frame count from their status files. Writes OUT/rss.csv and
      OUT/rss_summary.json (per service: RSS at start / middle / end / max, MiB, and the heap
      the process holds, from `heap_in_use_bytes` in its status file) and prints the summary.
"""
import csv
import json
import math
import os
import subprocess
import sys
import time


def read_lines(path):
    with open(path) as f:
        return [l.rstrip("\n") for l in f]


def palindrome(src, out, frames):
    cam = read_lines(os.path.join(src, "mav0/cam0/data.csv"))
    cam_head, cam_rows = cam[0], [r.split(",") for r in cam[1:] if r.strip()]
    m = len(cam_rows)
    assert m >= 2, "source has fewer than 2 frames"
    t_f = [int(r[0]) for r in cam_rows]
    dt = t_f[1] - t_f[0]
    assert all(b - a == dt for a, b in zip(t_f, t_f[1:])), "frames not evenly spaced"
    period = 2 * (m - 1)

    def src_pos(u):
        """Source position (in frames, continuous) and direction at output position u."""
        j = math.fmod(u, period)
        return (j, 1.0) if j <= m - 1 else (period - j, -1.0)

    os.makedirs(os.path.join(out, "mav0/cam0"), exist_ok=True)
    os.makedirs(os.path.join(out, "mav0/imu0"), exist_ok=True)
    for rel in ["mav0/cam0/sensor.yaml", "mav0/imu0/sensor.yaml", "mav0/cam0/data"]:
        dst = os.path.join(out, rel)
        if not os.path.lexists(dst):
            os.symlink(os.path.abspath(os.path.join(src, rel)), dst)
    with open(os.path.join(out, "mav0/cam0/data.csv"), "w") as f:
        f.write(cam_head + "\n")
        for k in range(frames):
            i = int(round(src_pos(k)[0]))
            f.write(f"{t_f[0] + k * dt},{cam_rows[i][1]}\n")
    # Ground truth (TUM, one pose per source frame).
    gt = read_lines(os.path.join(src, "groundtruth_cam0.txt"))
    gt_head = [l for l in gt if l.startswith("#")]
    gt_rows = [l.split() for l in gt if l.strip() and not l.startswith("#")]
    assert len(gt_rows) == m, "one ground-truth pose per frame expected"
    with open(os.path.join(out, "groundtruth_cam0.txt"), "w") as f:
        for h in gt_head:
            f.write(h + "\n")
        for k in range(frames):
            i = int(round(src_pos(k)[0]))
            t = t_f[0] + k * dt
            f.write(f"{t // 10**9}.{t % 10**9:09d} " + " ".join(gt_rows[i][1:]) + "\n")
    # IMU: for each output sample time from the first frame on, the source sample at the
    # mapped time.
    imu = read_lines(os.path.join(src, "mav0/imu0/data.csv"))
    imu_head, imu_rows = imu[0], [r.split(",") for r in imu[1:] if r.strip()]
    t_i = [int(r[0]) for r in imu_rows]
    di = t_i[1] - t_i[0]
    n_imu = (frames - 1) * dt // di + 1
    with open(os.path.join(out, "mav0/imu0/data.csv"), "w") as f:
        f.write(imu_head + "\n")
        for s in range(n_imu):
            t = t_f[0] + s * di
            u, sign = src_pos((t - t_f[0]) / dt)
            t_src = t_f[0] + u * dt
            i = min(max(int(round((t_src - t_i[0]) / di)), 0), len(imu_rows) - 1)
            r = imu_rows[i]
            gyro = [f"{sign * float(v)!r}" for v in r[1:4]]
            f.write(",".join([str(t)] + gyro + r[4:7]) + "\n")
    print(f"{out}: {frames} frames ({frames * dt / 1e9 / 60:.1f} min of data) from {m} source "
          f"frames, {n_imu} IMU samples")


def status(out, name):
    try:
        with open(os.path.join(out, "status", name + ".json")) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def rss_kib(pid):
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def children(ppid):
    """{service name: pid} of the launcher's children (`shoal service NAME --client C`)."""
    found = {}
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as f:
                st = f.read()
            if int(st.rsplit(")", 1)[1].split()[1]) != ppid:
                continue
            with open(f"/proc/{pid}/cmdline") as f:
                cmd = f.read().split("\0")
        except (OSError, ValueError, IndexError):
            continue
        if len(cmd) < 3 or cmd[1] != "service":
            continue
        name = cmd[2].replace("-", "_")
        if "--client" in cmd:
            name += ":" + cmd[cmd.index("--client") + 1]
        found[name] = int(pid)
    return found


def run(shoal, dataset, out, every, extra):
    os.makedirs(out, exist_ok=True)
    args = [shoal, "run", "--lockstep", "--quiet", "--dataset", dataset, "--out", out] + extra
    print(" ".join(args), flush=True)
    p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    t0 = time.time()
    rows = []
    names = set()
    # Samples as they come (the summary and rss.csv are written at the end; stopping the
    # launcher with SIGINT ends the run cleanly and still writes them).
    raw = open(os.path.join(out, "rss_samples.jsonl"), "w")
    while p.poll() is None:
        kids = children(p.pid)
        row = {"t_s": round(time.time() - t0, 1), "launcher": rss_kib(p.pid)}
        for name, pid in kids.items():
            row[name] = rss_kib(pid)
            names.add(name)
            # Heap the process holds (glibc mallinfo2, written with its status file): RSS
            # growth without heap growth is the allocator's, not the program's.
            heap = status(out, name.replace(":", "_c")).get("heap_in_use_bytes")
            row["heap:" + name] = None if heap is None else heap // 1024
        m = status(out, "mapper").get("counters", {})
        row["map_keyframes"] = m.get("keyframes")
        row["map_points"] = m.get("points")
        row["frames"] = status(out, "tracker_c0").get("counters", {}).get("frames_received")
        if kids:
            rows.append(row)
            raw.write(json.dumps(row) + "\n")
            raw.flush()
        time.sleep(every)
    raw.close()
    log = p.stdout.read().decode(errors="replace")
    cols = (["t_s", "frames", "map_keyframes", "map_points", "launcher"] + sorted(names)
            + ["heap:" + n for n in sorted(names)])
    with open(os.path.join(out, "rss.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow(r)
    # Start: the first sample after 10% of the run (start-up and the first map built);
    # middle: half way; end: the last sample.
    def pick(frac):
        return rows[min(int(frac * (len(rows) - 1)), len(rows) - 1)] if rows else {}

    summary = {"wall_s": round(time.time() - t0, 1), "samples": len(rows), "services": {}}
    for name in ["launcher"] + sorted(names):
        vals = [r.get(name) for r in rows if r.get(name) is not None]
        mib = lambda v: None if v is None else round(v / 1024, 1)
        summary["services"][name] = {
            "start_mib": mib(pick(0.1).get(name)),
            "middle_mib": mib(pick(0.5).get(name)),
            "end_mib": mib(pick(1.0).get(name)),
            "max_mib": mib(max(vals)) if vals else None,
        }
        if name != "launcher":
            h = "heap:" + name
            summary["services"][name].update({
                "heap_start_mib": mib(pick(0.1).get(h)),
                "heap_middle_mib": mib(pick(0.5).get(h)),
                "heap_end_mib": mib(pick(1.0).get(h)),
            })
    for key in ["frames", "map_keyframes", "map_points"]:
        summary[key] = {"start": pick(0.1).get(key), "middle": pick(0.5).get(key),
                        "end": pick(1.0).get(key)}
    with open(os.path.join(out, "rss_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(log[-1500:])
    print(json.dumps(summary, indent=1))
    return p.returncode


def main():
    a = sys.argv[1:]
    if len(a) == 4 and a[0] == "palindrome":
        palindrome(a[1], a[2], int(a[3]))
        return 0
    if len(a) >= 4 and a[0] == "run":
        extra = a[a.index("--") + 1:] if "--" in a else []
        head = a[: a.index("--")] if "--" in a else a
        every = 5.0
        if "--every" in head:
            every = float(head[head.index("--every") + 1])
        return run(head[1], head[2], head[3], every, extra)
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main())
