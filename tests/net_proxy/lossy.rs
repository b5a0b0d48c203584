//! A slow, lossy network between two network namespaces, made in user space because this
//! project's test machine has no `sch_netem`: one TUN device in each namespace, and threads
//! here that carry every IP packet from one to the other a fixed time late, dropping a
//! fraction of them. The packets are real ones (TCP segments, acknowledgements, SYNs), so a
//! drop costs what it costs on a real link: the kernel's retransmission, at least its
//! 200 ms minimum timeout when no later segment's duplicate acknowledgement recovers it.
//!
//! Needs root, `/dev/net/tun` and `ip netns` (the build script's `cfg(shoal_netns)`).
use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, FromRawFd};
use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// The server's address, in the server namespace.
pub const SERVER_ADDR: &str = "10.77.0.1";
/// The client's address, in the client namespace.
pub const CLIENT_ADDR: &str = "10.77.0.2";

/// Two namespaces (`server_ns`, `client_ns`) joined by the link; removed on drop.
pub struct LossyLink {
    pub server_ns: String,
    pub client_ns: String,
    stop: Arc<AtomicBool>,
    dropped: Arc<AtomicU64>,
    carried: Arc<AtomicU64>,
    threads: Vec<JoinHandle<()>>,
}

impl LossyLink {
    /// Makes the namespaces and the link: each packet `one_way` late, a fraction `loss` of
    /// them (in each direction, from a fixed random sequence) dropped.
    pub fn start(one_way: Duration, loss: f64) -> Self {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let tag = format!(
            "{}{}",
            std::process::id() % 100_000,
            NEXT.fetch_add(1, Ordering::SeqCst)
        );
        let (server_ns, client_ns) = (format!("shoal{tag}s"), format!("shoal{tag}c"));
        let mut ends = Vec::new();
        for (ns, addr, side) in [
            (&server_ns, SERVER_ADDR, 's'),
            (&client_ns, CLIENT_ADDR, 'c'),
        ] {
            let dev = format!("sl{tag}{side}");
            ip(&["netns", "add", ns]);
            let tun = open_tun(&dev);
            ip(&["link", "set", &dev, "netns", ns]);
            ip(&["-n", ns, "addr", "add", &format!("{addr}/24"), "dev", &dev]);
            ip(&["-n", ns, "link", "set", &dev, "up"]);
            ip(&["-n", ns, "link", "set", "lo", "up"]);
            ends.push(Arc::new(tun));
        }
        let mut link = Self {
            server_ns,
            client_ns,
            stop: Arc::default(),
            dropped: Arc::default(),
            carried: Arc::default(),
            threads: Vec::new(),
        };
        for (from, to, seed) in [(0, 1, 0x9e37_79b9_7f4a_7c15), (1, 0, 0xd1b5_4a32_d192_ed03)] {
            link.carry(ends[from].clone(), ends[to].clone(), one_way, loss, seed);
        }
        link
    }

    /// Packets dropped so far (both directions).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::SeqCst)
    }

    /// Packets carried so far (both directions).
    pub fn carried(&self) -> u64 {
        self.carried.load(Ordering::SeqCst)
    }

    /// `command` run inside namespace `ns` (through `ip netns exec`, which execs it: the
    /// child's pid is the command's).
    pub fn exec_in(ns: &str, command: &Command) -> Command {
        let mut cmd = Command::new("ip");
        cmd.args(["netns", "exec", ns]).arg(command.get_program());
        cmd.args(command.get_args());
        cmd
    }

    /// One direction: a reader that drops or timestamps each packet, a writer that sends
    /// it on when it is due.
    fn carry(&mut self, from: Arc<File>, to: Arc<File>, late: Duration, loss: f64, seed: u64) {
        let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
        let (stop, dropped, carried) = (
            self.stop.clone(),
            self.dropped.clone(),
            self.carried.clone(),
        );
        self.threads.push(std::thread::spawn(move || {
            let mut rng = seed;
            let mut buf = vec![0u8; 65_536];
            while !stop.load(Ordering::SeqCst) {
                if !readable(&from, 100) {
                    continue;
                }
                let Ok(n) = (&*from).read(&mut buf) else {
                    break;
                };
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                if ((rng >> 11) as f64 / (1u64 << 53) as f64) < loss {
                    dropped.fetch_add(1, Ordering::SeqCst);
                } else if tx.send((Instant::now() + late, buf[..n].to_vec())).is_err() {
                    break;
                }
            }
        }));
        let stop = self.stop.clone();
        self.threads.push(std::thread::spawn(move || {
            while !stop.load(Ordering::SeqCst) {
                let Ok((due, packet)) = rx.recv_timeout(Duration::from_millis(100)) else {
                    continue;
                };
                std::thread::sleep(due.saturating_duration_since(Instant::now()));
                if (&*to).write(&packet).is_ok() {
                    carried.fetch_add(1, Ordering::SeqCst);
                }
            }
        }));
    }
}

impl Drop for LossyLink {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
        for ns in [&self.server_ns, &self.client_ns] {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// Runs `ip args`, panicking (failing the test) with its message if it fails.
fn ip(args: &[&str]) {
    let out = Command::new("ip").args(args).output().expect("run ip");
    assert!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A new TUN device `name` (IP packets, no packet-information header).
fn open_tun(name: &str) -> File {
    const TUNSETIFF: libc::c_ulong = 0x4004_54ca;
    #[repr(C)]
    struct IfReq {
        name: [u8; 16],
        flags: libc::c_short,
        _pad: [u8; 22],
    }
    let path = c"/dev/net/tun";
    // SAFETY: a plain open of a NUL-terminated path.
    let fd = unsafe { libc::open(path.as_ptr(), libc::O_RDWR | libc::O_CLOEXEC) };
    assert!(
        fd >= 0,
        "open /dev/net/tun: {}",
        std::io::Error::last_os_error()
    );
    // SAFETY: `fd` was just opened and is owned by the File from here on.
    let file = unsafe { File::from_raw_fd(fd) };
    let mut req = IfReq {
        name: [0; 16],
        flags: (libc::IFF_TUN | libc::IFF_NO_PI) as libc::c_short,
        _pad: [0; 22],
    };
    req.name[..name.len()].copy_from_slice(name.as_bytes());
    // SAFETY: TUNSETIFF reads and writes an `ifreq`, which `IfReq` lays out (40 bytes).
    let rc = unsafe { libc::ioctl(file.as_raw_fd(), TUNSETIFF as _, &mut req) };
    assert!(
        rc == 0,
        "TUNSETIFF {name}: {}",
        std::io::Error::last_os_error()
    );
    file
}

/// Whether `f` has data within `timeout_ms`.
fn readable(f: &File, timeout_ms: i32) -> bool {
    let mut p = libc::pollfd {
        fd: f.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    // SAFETY: one valid pollfd.
    unsafe { libc::poll(&mut p, 1, timeout_ms) > 0 && p.revents & libc::POLLIN != 0 }
}
