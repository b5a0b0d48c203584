"""Issue 19's fault target, measured: every service SIGKILLed once in a visual-inertial
two-agent run (BENCHMARKS.md, "The visual-inertial server", "Faults").

`four-agents` agents 0 and 1 (seed 3, 640 frames: one lap each), `shoal run --lockstep
--mode vio --set tracker.window=10`: N fault-free runs (two lock-step clients are not
bit-deterministic: their spread is the reference), then one run per kill (`--kill
SERVICE@fK`). Per run: the joint server keyframe ATE of both clients (SE(3) and Sim(3):
`keyframes_server_c{i}.txt` against the truths, each agent's times shifted by 10 000 s so
that poses never associate across agents, `shoal eval --json`), the maps at the end, per
client keyframes sent / applied / with an IMU segment and the segments' samples (the
tracker's counts of what it sent, the report's of what the mapper journaled), unlinked
server keyframes (`imu_segments_server_c{i}.txt`), the server's visual-inertial local BAs,
and the kills' recovery times. Standard library only.

usage: vi_faults.py SHOAL_BINARY WORK_DIR [FAULT_FREE_RUNS] [KILL_FRAME]
"""
import json
import os
import subprocess
import sys

KILLS = ['camera_ingest:0', 'imu_ingest:0', 'tracker:0', 'tracker:1', 'mapper', 'loop_closer']


def shoal(binary, *args, **kw):
    return subprocess.run([binary, *args], check=True, capture_output=True, text=True, **kw)


def shifted(path, shift_s, out):
    for line in open(path):
        f = line.split()
        if line.startswith('#') or len(f) != 8:
            continue
        out.write(' '.join([f'{float(f[0]) + shift_s:.9f}', *f[1:]]) + '\n')


def joint_ate(binary, out, data, align):
    est, gt = os.path.join(out, 'joint_est.txt'), os.path.join(out, 'joint_gt.txt')
    with open(est, 'w') as e, open(gt, 'w') as g:
        for c in range(2):
            shifted(os.path.join(out, f'keyframes_server_c{c}.txt'), 10000 * c, e)
            shifted(os.path.join(data, f'agent{c}', 'groundtruth_cam0.txt'), 10000 * c, g)
    j = json.loads(shoal(binary, 'eval', '--est', est, '--gt', gt, '--align', align, '--json').stdout)
    return j['ate']['rmse'], j['scale']


def unlinked(out, c):
    rows = [list(map(int, l.split())) for l in open(os.path.join(out, f'imu_segments_server_c{c}.txt'))
            if not l.startswith('#')]
    return sum(1 for a, b in zip(rows, rows[1:]) if not (b[6] == 1 and b[1] == a[2]))


def run(binary, work, data, name, kills):
    out = os.path.join(work, name)
    args = ['run', '--out', out, '--quiet', '--ipc-prefix', f'vif_{name}_', '--lockstep',
            '--mode', 'vio', '--set', 'tracker.window=10']
    for c in range(2):
        args += ['--dataset', os.path.join(data, f'agent{c}')]
    for k in kills:
        args += ['--kill', k]
    shoal(binary, *args)
    r = json.load(open(os.path.join(out, 'report.json')))
    se3, _ = joint_ate(binary, out, data, 'se3')
    sim3, scale = joint_ate(binary, out, data, 'sim3')
    m = r['services']['mapper']['counters']
    clients = []
    for c in range(2):
        cl, t = r['clients'][c], r['services'][f'tracker:{c}']['counters']
        clients.append(
            f"c{c} {cl['keyframes_sent']}/{cl['keyframes_applied']} kf, "
            f"segments {t.get('keyframes_with_imu')}/{cl['keyframes_with_imu']} "
            f"({t.get('keyframe_imu_samples')}/{cl['keyframe_imu_samples']} samples), "
            f"unlinked {unlinked(out, c)}, VI BAs {m.get(f'c{c}.vi_windows')}")
    maps = '; '.join(f"{x['clients']} {'metric' if x['metric'] else 'visual'}" for x in r['maps'])
    rec = ', '.join(f"{f['service']}@f{f['at_frame']} {f['recovery_s']:.3f} s" for f in r['faults'])
    print(f"| {name} | {se3:.4f} | {sim3:.4f} ({scale:.4f}) | {maps} | {' · '.join(clients)} "
          f"| {rec or '-'} | {len(r['error_counts'])} |", flush=True)


def main():
    binary, work = sys.argv[1], sys.argv[2]
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 5
    at = int(sys.argv[4]) if len(sys.argv) > 4 else 320
    data = os.path.join(work, 'data')
    if not os.path.isdir(os.path.join(data, 'agent1')):
        shoal(binary, 'sim', '--scenario', 'four-agents', '--seed', '3', '--frames', '640', '--out', data)
    print('| run | joint SE(3) ATE, m | Sim(3) ATE, m (scale) | maps | per client: keyframes sent/applied, '
          'segments sent/journaled (samples), unlinked server keyframes, server VI BAs | kill, recovery '
          '| error kinds |')
    print('|---|---|---|---|---|---|---|')
    for i in range(n):
        run(binary, work, data, f'fault-free-{i + 1}', [])
    for k in KILLS:
        run(binary, work, data, f"kill-{k.replace(':', '')}", [f'{k}@f{at}'])


if __name__ == '__main__':
    main()
