//! A TCP relay between the clients and the server of the remote tests, standing for the
//! network: it can cut every connection (both ends closed, as a reset would), stop carrying
//! bytes for a while (a partition: nothing is lost on the sockets, nothing passes, new
//! connections are refused) and delay every byte by a fixed time each way (a long round
//! trip). Packet loss cannot be made under TCP by a relay; [`lossy::LossyLink`] makes it
//! below TCP, between two network namespaces (`tc netem` would do both in the kernel, but
//! its `sch_netem` module is not on every test machine, not on this project's).
#[cfg_attr(not(shoal_netns), allow(dead_code))]
pub mod lossy;

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

/// The relay's shared state.
#[derive(Default)]
struct State {
    /// No byte passes and new connections are closed at once.
    partitioned: AtomicBool,
    /// Both sockets of every connection so far (for [`Relay::cut`]).
    sockets: Mutex<Vec<TcpStream>>,
    /// Connections carried so far.
    connections: std::sync::atomic::AtomicU64,
    /// The first [`CAPTURE_BYTES`] the clients sent (what an eavesdropper would see).
    captured: Mutex<Vec<u8>>,
}

/// How much of the clients' bytes a relay keeps.
const CAPTURE_BYTES: usize = 8 << 20;

/// A relay from a local port to `127.0.0.1:upstream`.
pub struct Relay {
    /// The port clients connect to.
    pub port: u16,
    state: Arc<State>,
}

impl Relay {
    /// Starts relaying a new local port to `upstream`, each byte `one_way` late.
    pub fn start(upstream: u16, one_way: Duration) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind the relay");
        let port = listener.local_addr().unwrap().port();
        let state = Arc::new(State::default());
        let st = state.clone();
        std::thread::spawn(move || {
            for inbound in listener.incoming().flatten() {
                if st.partitioned.load(Ordering::SeqCst) {
                    let _ = inbound.shutdown(Shutdown::Both);
                    continue;
                }
                let Ok(outbound) = TcpStream::connect(("127.0.0.1", upstream)) else {
                    continue;
                };
                st.connections.fetch_add(1, Ordering::SeqCst);
                for s in [&inbound, &outbound] {
                    let _ = s.set_nodelay(true);
                    st.sockets.lock().unwrap().push(s.try_clone().unwrap());
                }
                pipe(&inbound, &outbound, one_way, &st, true);
                pipe(&outbound, &inbound, one_way, &st, false);
            }
        });
        Self { port, state }
    }

    /// Closes every connection now (both ends), as a reset would.
    pub fn cut(&self) {
        for s in self.state.sockets.lock().unwrap().drain(..) {
            let _ = s.shutdown(Shutdown::Both);
        }
    }

    /// Starts or ends a partition.
    pub fn partition(&self, on: bool) {
        self.state.partitioned.store(on, Ordering::SeqCst);
    }

    /// Connections carried so far.
    pub fn connections(&self) -> u64 {
        self.state.connections.load(Ordering::SeqCst)
    }

    /// Whether the clients' bytes so far (the first 8 MB) contain `needle`.
    pub fn saw(&self, needle: &[u8]) -> bool {
        let bytes = self.state.captured.lock().unwrap();
        bytes.windows(needle.len()).any(|w| w == needle)
    }
}

/// Carries `from` → `to`, each chunk `delay` after it was read, holding (not reading) while
/// partitioned; keeps a copy of what it carries when `capture`.
fn pipe(from: &TcpStream, to: &TcpStream, delay: Duration, st: &Arc<State>, capture: bool) {
    let (mut from, mut to) = (from.try_clone().unwrap(), to.try_clone().unwrap());
    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
    let st = st.clone();
    std::thread::spawn(move || {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            while st.partitioned.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(20));
            }
            match from.read(&mut buf) {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    if capture {
                        let mut c = st.captured.lock().unwrap();
                        let room = CAPTURE_BYTES.saturating_sub(c.len()).min(n);
                        c.extend_from_slice(&buf[..room]);
                    }
                    if tx
                        .send((Instant::now() + delay, buf[..n].to_vec()))
                        .is_err()
                    {
                        break;
                    }
                }
            }
        }
    });
    std::thread::spawn(move || {
        for (due, bytes) in rx {
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
            if to.write_all(&bytes).is_err() {
                break;
            }
        }
        let _ = to.shutdown(Shutdown::Write);
    });
}
