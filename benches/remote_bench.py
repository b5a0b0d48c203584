#!/usr/bin/env python3
"""Remote clients (issue 22): `shoal serve` and N `shoal client`s on this host, real time,
through loopback or through a slow, lossy link between two network namespaces.

The link is the one of `tests/net_proxy/lossy.rs`, made here in Python for the benchmark: a
TUN device in each namespace, and a thread that carries every IP packet from one to the
other `--one-way-ms` late, dropping a fraction `--loss` of them in each direction (this
machine has no `sch_netem`; the packets are real TCP segments, so a drop costs a real
retransmission). Needs root, /dev/net/tun and `ip netns`. Every run uses generated
credentials (`--auth`; off loopback the server needs them): client i is line i of the file,
so its slot is i, the client index a single-host `shoal run` with the same datasets gives.

Prints one table row per client: keyframes sent / acked / applied, round trip p50 / p99,
bytes per keyframe, frames posed, tracking latency p50 / p99, and the server keyframes' ATE
(`shoal eval --align sim3`) against the dataset's ground truth; then the server's maps.

    python3 benches/remote_bench.py --shoal target/release/shoal --data /tmp/d/two480 \
        --clients 2 --one-way-ms 25 --loss 0.01 --out /tmp/d/rb_loss
The data folder is `shoal sim --scenario two-agents --frames 480 --out DIR`; client i runs
agent (i mod 2).
"""
import argparse
import fcntl
import heapq
import json
import os
import random
import select
import shutil
import signal
import struct
import subprocess
import threading
import time

TUNSETIFF = 0x400454CA
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000


class Link:
    """Two namespaces joined by TUN devices, `one_way` s late, `loss` dropped each way."""

    def __init__(self, tag, one_way, loss, seed=1):
        self.ns = (f"rb{tag}s", f"rb{tag}c")
        self.addr = ("10.77.0.1", "10.77.0.2")
        self.fds = []
        for ns, addr, side in zip(self.ns, self.addr, "sc"):
            subprocess.run(["ip", "netns", "del", ns], stderr=subprocess.DEVNULL)
            sh("ip", "netns", "add", ns)
            dev = f"rb{tag}{side}"
            fd = os.open("/dev/net/tun", os.O_RDWR)
            fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", dev.encode(), IFF_TUN | IFF_NO_PI))
            os.set_blocking(fd, False)
            self.fds.append(fd)
            sh("ip", "link", "set", dev, "netns", ns)
            sh("ip", "-n", ns, "addr", "add", addr + "/24", "dev", dev)
            sh("ip", "-n", ns, "link", "set", dev, "up")
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        self.one_way, self.loss = one_way, loss
        self.rng = random.Random(seed)
        self.carried = self.dropped = 0
        self.stop = False
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self):
        a, b = self.fds
        peer = {a: b, b: a}
        queue, n = [], 0
        while not self.stop:
            now = time.monotonic()
            while queue and queue[0][0] <= now:
                _, _, fd, packet = heapq.heappop(queue)
                try:
                    os.write(fd, packet)
                    self.carried += 1
                except OSError:
                    pass
            timeout = max(0.0, queue[0][0] - now) if queue else 0.1
            ready, _, _ = select.select([a, b], [], [], timeout)
            for fd in ready:
                while True:
                    try:
                        packet = os.read(fd, 65536)
                    except BlockingIOError:
                        break
                    if self.rng.random() < self.loss:
                        self.dropped += 1
                        continue
                    n += 1
                    heapq.heappush(queue, (time.monotonic() + self.one_way, n, peer[fd], packet))

    def close(self):
        self.stop = True
        self.thread.join()
        for ns in self.ns:
            subprocess.run(["ip", "netns", "del", ns])


def sh(*args):
    subprocess.run(args, check=True)


def in_ns(ns, cmd):
    return ["ip", "netns", "exec", ns] + cmd if ns else cmd


def listening(pid, port):
    try:
        table = open(f"/proc/{pid}/net/tcp").read().splitlines()[1:]
    except OSError:
        return False
    return any(
        l.split()[1].endswith(f":{port:04X}") and l.split()[3] == "0A" for l in table
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shoal", default="target/release/shoal")
    ap.add_argument("--data", required=True)
    ap.add_argument("--clients", type=int, default=2)
    ap.add_argument("--one-way-ms", type=float, default=0.0)
    ap.add_argument("--loss", type=float, default=0.0)
    ap.add_argument("--port", type=int, default=7610)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--tls", action="store_true",
                    help="a tls/ endpoint with the test certificates of tests/tls")
    ap.add_argument("--initcwnd", type=int, default=0,
                    help="the link's route with this initcwnd and initrwnd, segments "
                         "(0: the kernel's 10)")
    ap.add_argument("--no-idle-restart", action="store_true",
                    help="sysctl net.ipv4.tcp_slow_start_after_idle=0 in both namespaces "
                         "(TCP keeps its window between keyframes)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    shoal = os.path.abspath(a.shoal)
    shutil.rmtree(a.out, ignore_errors=True)
    os.makedirs(a.out)
    tag = str(os.getpid() % 10000)
    link, host = None, "127.0.0.1"
    if a.one_way_ms > 0 or a.loss > 0:
        link = Link(tag, a.one_way_ms / 1000.0, a.loss)
        host = link.addr[0]
        if a.initcwnd:
            for ns, side in zip(link.ns, "sc"):
                sh("ip", "-n", ns, "route", "change", "10.77.0.0/24", "dev", f"rb{tag}{side}",
                   "initcwnd", str(a.initcwnd), "initrwnd", str(a.initcwnd))
        if a.no_idle_restart:
            for ns in link.ns:
                sh("ip", "netns", "exec", ns, "sysctl", "-qw",
                   "net.ipv4.tcp_slow_start_after_idle=0")
    # Credentials always (off loopback the server needs them): client i is the file's line
    # i, so it gets slot i whatever the order of arrival, as `shoal run` would number it.
    with open(f"{a.out}/clients.txt", "w") as f:
        for i in range(a.clients):
            f.write(f"c{i}:secret {i}\n")
    for i in range(a.clients):
        with open(f"{a.out}/c{i}.txt", "w") as f:
            f.write(f"c{i}:secret {i}\n")
    auth_srv = ["--auth", f"{a.out}/clients.txt"]
    auth_cli = lambda i: ["--auth", f"{a.out}/c{i}.txt"]
    srv_ns, cli_ns = (link.ns if link else (None, None))
    scheme = "tls" if a.tls else "tcp"
    endpoint = f"{scheme}/{host}:{a.port}"
    if a.tls:
        certs = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "tls")
        auth_srv += ["--tls-cert", f"{certs}/server.pem", "--tls-key", f"{certs}/server.key"]
        plain_cli = auth_cli
        auth_cli = lambda i: plain_cli(i) + ["--tls-ca", f"{certs}/ca.pem"]
    server = subprocess.Popen(
        in_ns(srv_ns, [shoal, "serve", "--listen", endpoint, "--out", f"{a.out}/server",
                       "--clients", str(a.clients), "--ipc-prefix", f"rb{tag}s_"] + auth_srv),
        stdout=subprocess.DEVNULL, stderr=open(f"{a.out}/server.log", "w"))
    deadline = time.monotonic() + 60
    while not listening(server.pid, a.port):
        assert time.monotonic() < deadline and server.poll() is None, "server never listened"
        time.sleep(0.1)
    clients = []
    for i in range(a.clients):
        cmd = [shoal, "client", "--connect", endpoint, "--dataset", f"{a.data}/agent{i % 2}",
               "--out", f"{a.out}/c{i}", "--name", f"c{i}", "--quiet", "--mode", "mono",
               "--rate", "1", "--set", f"tracker.window={a.window}",
               "--ipc-prefix", f"rb{tag}c{i}_"] + auth_cli(i)
        clients.append(subprocess.Popen(in_ns(cli_ns, cmd), stdout=subprocess.DEVNULL,
                                        stderr=open(f"{a.out}/c{i}.log", "w")))
    for c in clients:
        c.wait()
    server.send_signal(signal.SIGINT)
    server.wait()
    if link:
        link.close()
        print(f"link: {a.one_way_ms:.0f} ms each way, loss {a.loss:.3f}: "
              f"{link.carried} packets carried, {link.dropped} dropped")
    report(a, shoal)


def report(a, shoal):
    srv = json.load(open(f"{a.out}/server/report.json"))
    table = {c["name"]: c for c in srv["remote_clients"]}
    print("| client | sent / acked / applied | round trip p50 / p99 ms | bytes per keyframe "
          "| frames posed | tracking p50 / p99 ms | server keyframes ATE mm |")
    print("|---|---|---|---|---|---|---|")
    for i in range(a.clients):
        rep = json.load(open(f"{a.out}/c{i}/report.json"))
        c, br = rep["clients"][0], rep["bridges"]["bridge:0"]
        me = table.get(f"c{i}", {})
        lat = c["latency_ms_publish_to_pose"]
        ate = "-"
        est = f"{a.out}/server/keyframes_server_c{me.get('slot', i)}.txt"
        if os.path.exists(est):
            out = subprocess.run([shoal, "eval", "--est", est, "--gt",
                                  f"{a.data}/agent{i % 2}/groundtruth_cam0.txt",
                                  "--align", "sim3", "--json"], capture_output=True, text=True)
            try:
                ev = json.loads(out.stdout)
                ate = f"{ev['ate']['rmse'] * 1000:.1f} ({ev['n_associated']} kf)"
            except (ValueError, KeyError):
                ate = out.stdout.strip()[-80:] or out.stderr.strip()[-80:]
        print(f"| c{i} | {c['keyframes_sent']} / {c['keyframes_acked']} / "
              f"{me.get('keyframes_applied', 0)} | {br['roundtrip_us_p50'] / 1000:.1f} / "
              f"{br['roundtrip_us_p99'] / 1000:.1f} | "
              f"{br['keyframe_bytes'] / max(1, br['keyframes_forwarded']) / 1000:.1f} kB | "
              f"{c['frames_posed']} / {c['frames_total']} | {lat['p50']:.1f} / {lat['p99']:.1f} "
              f"| {ate} |")
    print(f"server: merges {srv['merges']}, maps {json.dumps(srv['maps'])[:300]}")


if __name__ == "__main__":
    main()
