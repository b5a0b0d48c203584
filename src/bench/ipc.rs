//! `shoal bench ipc`: one-way frame hand-off latency between two processes, from the moment
//! the publisher hands a filled frame over to the moment the subscriber process holds it.
//!
//! Methods (the same gray frame, same pacing, the subscriber is a child process):
//! - `iceoryx2_poll`: zero-copy sample in shared memory, subscriber busy-polls `receive()`;
//! - `iceoryx2_event`: the same, the subscriber sleeps in a WaitSet and is woken by an
//!   iceoryx2 event the publisher notifies after `send()`;
//! - `uds_copy`: the copying baseline: the frame bytes are written to a Unix domain stream
//!   socket and read into the subscriber's buffer (two copies through the kernel).
//!
//! The publisher stamps CLOCK_MONOTONIC right before the hand-off (`send()` / `write_all`);
//! the subscriber stamps when it holds the whole frame. The first 100 frames are warm-up.
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use iceoryx2::prelude::*;
use serde::{Deserialize, Serialize};
use shm_schema::time::monotonic_ns;
use shm_schema::topics::{self, Ipc};
use shm_schema::{FrameHeader, MsgMeta};

use crate::launcher::recorder::LatencyHist;

const WARMUP: usize = 100;

/// Arguments of `shoal bench ipc`.
#[derive(clap::Args, Debug)]
pub struct IpcArgs {
    /// Frames per (size, method).
    #[arg(long, default_value_t = 10_000)]
    pub frames: usize,
    /// Gap between frames, µs.
    #[arg(long, default_value_t = 500)]
    pub period_us: u64,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Only these methods (comma separated).
    #[arg(long, default_value = "iceoryx2_poll,iceoryx2_event,uds_copy")]
    pub methods: String,
}

/// Arguments of the subscriber process.
#[derive(clap::Args, Debug)]
pub struct PeerArgs {
    /// Method.
    #[arg(long)]
    pub method: String,
    /// Frame width.
    #[arg(long)]
    pub width: u32,
    /// Frame height.
    #[arg(long)]
    pub height: u32,
    /// Frames to receive (warm-up included).
    #[arg(long)]
    pub frames: usize,
    /// iceoryx2 prefix.
    #[arg(long)]
    pub prefix: String,
    /// Unix socket path (uds_copy).
    #[arg(long, default_value = "")]
    pub socket: String,
}

/// One result row of the JSON contract.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IpcResult {
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// `iceoryx2_poll`, `iceoryx2_event` or `uds_copy`.
    pub method: String,
    /// Frames measured (after warm-up).
    pub n: u64,
    /// Median, µs.
    pub p50_us: f64,
    /// 90th percentile, µs.
    pub p90_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
    /// Largest, µs.
    pub max_us: f64,
}

#[derive(Serialize)]
struct IpcReport {
    results: Vec<IpcResult>,
}

fn bench_client(width: u32) -> u32 {
    100 + width
}

fn event_service(
    node: &Node<Ipc>,
    width: u32,
) -> anyhow::Result<iceoryx2::service::port_factory::event::PortFactory<Ipc>> {
    let name = ServiceName::new(&topics::host_topic(&format!("bench/event_{width}")))
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    node.service_builder(&name)
        .event()
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))
}

/// One measurement: a subscriber process for `method` at `w` x `h`, `args.frames` frames.
fn measure(
    args: &IpcArgs,
    node: &Node<Ipc>,
    prefix: &str,
    (w, h): (u32, u32),
    method: &str,
) -> anyhow::Result<IpcResult> {
    let bytes = (w * h) as usize;
    let socket = std::env::temp_dir().join(format!("shoal_bench_{}.sock", std::process::id()));
    let _ = std::fs::remove_file(&socket);
    let listener = if method == "uds_copy" {
        Some(UnixListener::bind(&socket)?)
    } else {
        None
    };
    let frames = topics::frames_service(node, bench_client(w))?;
    let publisher = topics::frame_publisher(&frames, bytes, bench_client(w))?;
    let events = event_service(node, w)?;
    let notifier = events
        .notifier_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let mut child = Command::new(std::env::current_exe()?)
        .args(["bench", "ipc-peer", "--method", method])
        .args(["--width", &w.to_string(), "--height", &h.to_string()])
        .args(["--frames", &args.frames.to_string(), "--prefix", prefix])
        .args(["--socket", &socket.display().to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .context("starting the subscriber process")?;
    let mut lines = BufReader::new(child.stdout.take().context("child stdout")?).lines();
    let first = lines.next().context("subscriber ended early")??;
    anyhow::ensure!(
        first.trim() == "READY",
        "unexpected subscriber line: {first}"
    );
    let mut stream = match &listener {
        Some(l) => Some(l.accept()?.0),
        None => None,
    };
    std::thread::sleep(Duration::from_millis(50));
    let sender = Sender {
        publisher: &publisher,
        notifier: &notifier,
        size: (w, h),
    };
    match stream.as_mut() {
        Some(s) => sender.stream_uds(args, s)?,
        None => {
            sender.publish(args, method == "iceoryx2_event")?;
            sender.end_of_stream(args.frames)?;
        }
    }
    let result_line = lines.next().context("subscriber gave no result")??;
    let _ = child.wait();
    let _ = std::fs::remove_file(&socket);
    Ok(serde_json::from_str(&result_line)?)
}

/// The publisher side of one measurement.
struct Sender<'a> {
    publisher: &'a iceoryx2::port::publisher::Publisher<Ipc, [u8], FrameHeader>,
    notifier: &'a iceoryx2::port::notifier::Notifier<Ipc>,
    size: (u32, u32),
}

impl Sender<'_> {
    fn image(&self) -> Vec<u8> {
        let bytes = (self.size.0 * self.size.1) as usize;
        (0..bytes).map(|i| (i * 31 % 251) as u8).collect()
    }

    /// Sleeps (not spins) until `next`, so the subscriber has a core of its own.
    fn pace(next: i64) {
        let left = next - monotonic_ns();
        if left > 0 {
            std::thread::sleep(Duration::from_nanos(left as u64));
        }
    }

    /// The frames through a Unix socket: a copy per frame, stamp first.
    fn stream_uds(&self, args: &IpcArgs, s: &mut UnixStream) -> anyhow::Result<()> {
        let image = self.image();
        let mut wire = vec![0u8; 8 + image.len()];
        for _ in 0..args.frames {
            let next = monotonic_ns() + args.period_us as i64 * 1000;
            wire[8..].copy_from_slice(&image);
            wire[..8].copy_from_slice(&monotonic_ns().to_le_bytes());
            s.write_all(&wire)?;
            Self::pace(next);
        }
        Ok(())
    }

    /// The frames through iceoryx2 (with an event notification per frame if `notify`).
    fn publish(&self, args: &IpcArgs, notify: bool) -> anyhow::Result<()> {
        let image = self.image();
        let (w, h) = self.size;
        for k in 0..args.frames {
            let next = monotonic_ns() + args.period_us as i64 * 1000;
            let mut sample = self.publisher.loan_slice(image.len())?;
            sample.payload_mut().copy_from_slice(&image);
            let meta = MsgMeta::new(0, 0, k as u64, monotonic_ns());
            *sample.user_header_mut() = FrameHeader {
                meta,
                width: w,
                height: h,
                stride: w,
                ..Default::default()
            };
            sample.send()?;
            if notify {
                self.notifier
                    .notify()
                    .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            }
            Self::pace(next);
        }
        Ok(())
    }

    /// End of stream, a few times: the subscriber stops at the first it sees.
    fn end_of_stream(&self, frames: usize) -> anyhow::Result<()> {
        let bytes = (self.size.0 * self.size.1) as usize;
        for _ in 0..5 {
            let mut sample = self.publisher.loan_slice(bytes)?;
            let mut meta = MsgMeta::new(0, 0, frames as u64, monotonic_ns());
            meta.flags = shm_schema::FLAG_END_OF_STREAM;
            *sample.user_header_mut() = FrameHeader {
                meta,
                ..Default::default()
            };
            sample.send()?;
            self.notifier
                .notify()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            std::thread::sleep(Duration::from_millis(2));
        }
        Ok(())
    }
}

/// Prints zero-copy vs socket-copy per size.
fn print_summary(report: &IpcReport) {
    for (w, h) in [(752u32, 480u32), (1280, 720)] {
        let get = |m: &str| {
            report
                .results
                .iter()
                .find(|r| r.width == w && r.height == h && r.method == m)
        };
        if let (Some(a), Some(b)) = (get("iceoryx2_poll"), get("uds_copy")) {
            println!(
                "{w}x{h}: zero-copy p50 {:.1} µs vs Unix-socket copy p50 {:.1} µs ({:.0}x lower)",
                a.p50_us,
                b.p50_us,
                b.p50_us / a.p50_us.max(1e-3)
            );
        }
    }
}

/// Runs the benchmark (publisher side).
pub fn run(args: &IpcArgs) -> anyhow::Result<()> {
    let prefix = format!("shoal_bench_{}_", std::process::id());
    let node = topics::create_node("bench_ipc_pub", &prefix)?;
    let mut results = Vec::new();
    for size in [(752u32, 480u32), (1280, 720)] {
        for method in args.methods.split(',').map(str::trim) {
            let r = measure(args, &node, &prefix, size, method)?;
            if !args.json {
                eprintln!(
                    "{:>4}x{:<4} {:<15} n={:<6} p50 {:>9.1} µs  p90 {:>9.1} µs  p99 {:>9.1} µs  max {:>9.1} µs",
                    r.width, r.height, r.method, r.n, r.p50_us, r.p90_us, r.p99_us, r.max_us
                );
            }
            results.push(r);
        }
    }
    let report = IpcReport { results };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print_summary(&report);
    }
    Ok(())
}

/// The subscriber's side of one method: fills `hist` until the end of stream.
struct Receiver<'a> {
    args: &'a PeerArgs,
    subscriber: &'a iceoryx2::port::subscriber::Subscriber<Ipc, [u8], FrameHeader>,
    hist: LatencyHistNs,
    /// Frames seen (the first [`WARMUP`] are not recorded).
    k: usize,
}

impl Receiver<'_> {
    fn bytes(&self) -> usize {
        (self.args.width * self.args.height) as usize
    }

    /// A frame taken at `now` with stamp `t` and `probe`, a pixel read from it.
    fn record(&mut self, now: i64, t: i64, probe: u8) {
        if self.k >= WARMUP {
            self.hist.record(now - t, probe);
        }
        self.k += 1;
    }

    fn uds(&mut self, ready: &mut impl Write) -> anyhow::Result<()> {
        writeln!(ready, "READY")?;
        ready.flush()?;
        let mut s = UnixStream::connect(&self.args.socket)?;
        let bytes = self.bytes();
        let mut buf = vec![0u8; 8 + bytes];
        for _ in 0..self.args.frames {
            s.read_exact(&mut buf)?;
            let now = monotonic_ns();
            let t = i64::from_le_bytes(buf[..8].try_into()?);
            self.record(now, t, buf[8 + bytes / 2]);
        }
        Ok(())
    }

    /// Takes every waiting sample; `true` at the end of stream.
    fn drain(&mut self) -> anyhow::Result<bool> {
        let mid = self.bytes() / 2;
        while let Some(sample) = self.subscriber.receive()? {
            let now = monotonic_ns();
            if sample.user_header().meta.is_end_of_stream() {
                return Ok(true);
            }
            let t = sample.user_header().meta.publish_mono_ns;
            self.record(now, t, sample.payload()[mid]);
        }
        Ok(false)
    }

    fn poll(&mut self, ready: &mut impl Write) -> anyhow::Result<()> {
        writeln!(ready, "READY")?;
        ready.flush()?;
        while !self.drain()? {
            std::hint::spin_loop();
        }
        Ok(())
    }

    fn event(
        &mut self,
        ready: &mut impl Write,
        listener: &iceoryx2::port::listener::Listener<Ipc>,
    ) -> anyhow::Result<()> {
        let waitset = WaitSetBuilder::new()
            .create::<Ipc>()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let guard = waitset
            .attach_notification(listener)
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        writeln!(ready, "READY")?;
        ready.flush()?;
        let mut done = false;
        while !done {
            let mut result = Ok(false);
            waitset
                .wait_and_process_once(|id| {
                    if id.has_event_from(&guard) {
                        let _ = listener.try_wait(|_| {});
                        result = self.drain();
                    }
                    CallbackProgression::Continue
                })
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            done = result.context("receive")?;
        }
        Ok(())
    }
}

/// The subscriber process: receives `frames` frames and prints one JSON result line.
pub fn peer(args: &PeerArgs) -> anyhow::Result<()> {
    let node = topics::create_node("bench_ipc_sub", &args.prefix)?;
    let frames = topics::frames_service(&node, bench_client(args.width))?;
    let subscriber = topics::frame_subscriber(&frames, bench_client(args.width))?;
    let events = event_service(&node, args.width)?;
    let listener = events
        .listener_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let mut out = std::io::stdout().lock();
    let mut rx = Receiver {
        args,
        subscriber: &subscriber,
        hist: LatencyHistNs::default(),
        k: 0,
    };
    match args.method.as_str() {
        "uds_copy" => rx.uds(&mut out)?,
        "iceoryx2_poll" => rx.poll(&mut out)?,
        "iceoryx2_event" => rx.event(&mut out, &listener)?,
        m => anyhow::bail!("unknown method '{m}'"),
    }
    let p = rx.hist.hist.percentiles();
    let us = |ms: f64| ms * 1000.0;
    let r = IpcResult {
        width: args.width,
        height: args.height,
        method: args.method.clone(),
        n: p.n,
        p50_us: us(p.p50),
        p90_us: us(p.p90),
        p99_us: us(p.p99),
        max_us: us(p.max),
    };
    writeln!(out, "{}", serde_json::to_string(&r)?)?;
    std::hint::black_box(rx.hist.touched);
    Ok(())
}

/// Histogram in ns resolution for sub-µs hand-offs (reported in µs).
#[derive(Default)]
struct LatencyHistNs {
    hist: HistNs,
    touched: u64,
}

impl LatencyHistNs {
    fn record(&mut self, ns: i64, byte: u8) {
        self.touched = self.touched.wrapping_add(byte as u64);
        self.hist.record(ns);
    }
}

/// A thin wrapper that reuses the recorder's µs histogram but keeps 0.1 µs resolution by
/// recording in units of 100 ns.
#[derive(Default)]
struct HistNs(LatencyHist);

impl HistNs {
    fn record(&mut self, ns: i64) {
        // LatencyHist records ns / 1000 µs; feed ns * 10 so one unit is 100 ns.
        self.0.record_ns(ns.max(0) * 10);
    }

    fn percentiles(&self) -> crate::launcher::recorder::Percentiles {
        let mut p = self.0.percentiles();
        for v in [&mut p.p50, &mut p.p90, &mut p.p99, &mut p.max, &mut p.mean] {
            *v /= 10.0;
        }
        p
    }
}
