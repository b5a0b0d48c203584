import os, sys, time, subprocess, json
# Runs `shoal run --rate 1.0` with N clients and sums the CPU time of each child process
# (utime+stime from /proc/PID/stat, sampled every 0.5 s). Issue 4 benchmark (BENCHMARKS.md).
# usage: mapper_clients.py SHOAL_BINARY OUT N DATASET [DATASET...] [-- EXTRA_RUN_ARGS...]
# (datasets used round-robin; e.g. `-- --mode vio` for visual-inertial clients, issue 19)
B, out, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
rest = sys.argv[4:]
data, extra = (rest[:rest.index('--')], rest[rest.index('--') + 1:]) if '--' in rest else (rest, [])
args = [B, 'run', '--rate', '1.0', '--max-frames', '600', '--out', out, '--quiet', '--ipc-prefix', f'bn{n}_', '--tracker-arg=--window=10'] + extra
for i in range(n):
    args += ['--dataset', data[i % len(data)]]
p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
hz = os.sysconf('SC_CLK_TCK')
seen = {}
def sample():
    for pid in os.listdir('/proc'):
        if not pid.isdigit(): continue
        try:
            st = open(f'/proc/{pid}/stat').read()
            ppid = int(st.rsplit(')', 1)[1].split()[1])
            if ppid != p.pid and int(pid) != p.pid: continue
            f = st.rsplit(')', 1)[1].split()
            ticks = int(f[11]) + int(f[12])
            start = int(f[19])
            cmd = open(f'/proc/{pid}/cmdline').read().split('\0')
            name = ' '.join(cmd[1:5]) if int(pid) != p.pid else 'launcher'
            seen[pid] = (name, ticks, start)
        except Exception:
            pass
t0 = time.time()
while p.poll() is None:
    sample(); time.sleep(0.5)
wall = time.time() - t0
print(p.stdout.read().decode()[-600:])
up = float(open('/proc/uptime').read().split()[0])
res = {}
for pid, (name, ticks, start) in seen.items():
    res[name] = res.get(name, 0) + ticks / hz
print(json.dumps({'wall_s': wall, 'cpu_s': res}, indent=1))
try:
    rep = json.load(open(out + '/report.json'))
    for i, c in enumerate(rep['clients']):
        lat = c.get('latency_ms_publish_to_pose', {})
        print(f"c{i}: frames dropped {c['frames_dropped']} of {c['frames_total']}, keyframes sent/applied "
              f"{c.get('keyframes_sent')}/{c.get('keyframes_applied')}, publish->pose {lat}")
    print('maps', rep.get('maps'))
except Exception as e:
    print('report.json:', e)
json.dump({'wall_s': wall, 'cpu_s': res}, open(out + '/cpu.json', 'w'))
