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

/// Runs the benchmark (publisher side).
pub fn run(args: &IpcArgs) -> anyhow::Result<()> {
    let exe = std::env::current_exe()?;
    let prefix = format!("shoal_bench_{}_", std::process::id());
    let node = topics::create_node("bench_ipc_pub", &prefix)?;
    let mut results = Vec::new();
    for (w, h) in [(752u32, 480u32), (1280, 720)] {
        let bytes = (w * h) as usize;
        let image: Vec<u8> = (0..bytes).map(|i| (i * 31 % 251) as u8).collect();
        for method in args.methods.split(',').map(str::trim) {
            let socket =
                std::env::temp_dir().join(format!("shoal_bench_{}.sock", std::process::id()));
            let _ = std::fs::remove_file(&socket);
            let listener = if method == "uds_copy" {
                Some(UnixListener::bind(&socket)?)
            } else {
                None
            };
            let frames = topics::frames_service(&node, bench_client(w))?;
            let publisher = topics::frame_publisher(&frames, bytes, bench_client(w))?;
            let events = event_service(&node, w)?;
            let notifier = events
                .notifier_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            let mut child = Command::new(&exe)
                .args(["bench", "ipc-peer", "--method", method])
                .args(["--width", &w.to_string(), "--height", &h.to_string()])
                .args(["--frames", &args.frames.to_string(), "--prefix", &prefix])
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
            let mut wire = vec![0u8; 8 + bytes];
            for k in 0..args.frames {
                let next = monotonic_ns() + args.period_us as i64 * 1000;
                match method {
                    "uds_copy" => {
                        let s = stream.as_mut().context("socket")?;
                        wire[8..].copy_from_slice(&image);
                        let t = monotonic_ns();
                        wire[..8].copy_from_slice(&t.to_le_bytes());
                        s.write_all(&wire)?;
                    }
                    _ => {
                        let mut sample = publisher.loan_slice(bytes)?;
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
                        if method == "iceoryx2_event" {
                            notifier.notify().map_err(|e| anyhow::anyhow!("{e:?}"))?;
                        }
                    }
                }
                // Sleep (not spin) between frames so the subscriber has a core of its own.
                let left = next - monotonic_ns();
                if left > 0 {
                    std::thread::sleep(Duration::from_nanos(left as u64));
                }
            }
            if method != "uds_copy" {
                // End of stream (a few times: the subscriber stops at the first it sees).
                for _ in 0..5 {
                    let mut sample = publisher.loan_slice(bytes)?;
                    let mut meta = MsgMeta::new(0, 0, args.frames as u64, monotonic_ns());
                    meta.flags = shm_schema::FLAG_END_OF_STREAM;
                    *sample.user_header_mut() = FrameHeader {
                        meta,
                        ..Default::default()
                    };
                    sample.send()?;
                    notifier.notify().map_err(|e| anyhow::anyhow!("{e:?}"))?;
                    std::thread::sleep(Duration::from_millis(2));
                }
            }
            let result_line = lines.next().context("subscriber gave no result")??;
            let _ = child.wait();
            let _ = std::fs::remove_file(&socket);
            let r: IpcResult = serde_json::from_str(&result_line)?;
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
    Ok(())
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
    let mut hist = LatencyHistNs::default();
    let bytes = (args.width * args.height) as usize;
    let mut out = std::io::stdout().lock();
    match args.method.as_str() {
        "uds_copy" => {
            writeln!(out, "READY")?;
            out.flush()?;
            let mut s = UnixStream::connect(&args.socket)?;
            let mut buf = vec![0u8; 8 + bytes];
            for k in 0..args.frames {
                s.read_exact(&mut buf)?;
                let now = monotonic_ns();
                let t = i64::from_le_bytes(buf[..8].try_into()?);
                if k >= WARMUP {
                    hist.record(now - t, buf[8 + bytes / 2]);
                }
            }
        }
        "iceoryx2_poll" => {
            writeln!(out, "READY")?;
            out.flush()?;
            let mut k = 0;
            loop {
                if let Some(sample) = subscriber.receive()? {
                    let now = monotonic_ns();
                    if sample.user_header().meta.is_end_of_stream() {
                        break;
                    }
                    let t = sample.user_header().meta.publish_mono_ns;
                    if k >= WARMUP {
                        hist.record(now - t, sample.payload()[bytes / 2]);
                    }
                    k += 1;
                } else {
                    std::hint::spin_loop();
                }
            }
        }
        "iceoryx2_event" => {
            let waitset = WaitSetBuilder::new()
                .create::<Ipc>()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            let guard = waitset
                .attach_notification(&listener)
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            writeln!(out, "READY")?;
            out.flush()?;
            let mut k = 0;
            let mut done = false;
            while !done {
                let mut err = None;
                waitset
                    .wait_and_process_once(|id| {
                        if id.has_event_from(&guard) {
                            let _ = listener.try_wait(|_| {});
                            loop {
                                match subscriber.receive() {
                                    Ok(Some(sample)) => {
                                        let now = monotonic_ns();
                                        if sample.user_header().meta.is_end_of_stream() {
                                            done = true;
                                            break;
                                        }
                                        let t = sample.user_header().meta.publish_mono_ns;
                                        if k >= WARMUP {
                                            hist.record(now - t, sample.payload()[bytes / 2]);
                                        }
                                        k += 1;
                                    }
                                    Ok(None) => break,
                                    Err(e) => {
                                        err = Some(format!("{e:?}"));
                                        break;
                                    }
                                }
                            }
                        }
                        CallbackProgression::Continue
                    })
                    .map_err(|e| anyhow::anyhow!("{e:?}"))?;
                if let Some(e) = err {
                    anyhow::bail!("receive: {e}");
                }
            }
        }
        m => anyhow::bail!("unknown method '{m}'"),
    }
    let p = hist.hist.percentiles();
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
    std::hint::black_box(hist.touched);
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
