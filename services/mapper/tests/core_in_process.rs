//! The mapper's core fed in-process, without iceoryx2: the keyframes of the tracker's core
//! on a synthetic scene go in, the mapper's acknowledgements and pose feedback go back to
//! the tracker, and the loop keyframes it forwards are counted. Checks the keyframe
//! accounting of a clean run, a restart that rebuilds the maps from the journal and takes
//! re-sent keyframes as duplicates, and a malformed keyframe among good ones. Seconds, where
//! the process tests (`tests/mapper.rs`, `tests/kill_each.rs`) take minutes.
use std::time::{Duration, Instant};

use clap::Parser;
use crossbeam_channel::Receiver;
use datasets::sim::{Scenario, SimParams, SimWorld};
use mapper::core::{Mapper, Out as MapperOut};
use mapper::worker::Report;
use mapper::Params;
use shm_schema::{Feedback, ImuMsg, MsgMeta, FLAG_END_OF_STREAM, FLAG_HANDLED};
use shoal_runtime::{ErrorKind, Status};
use tracker::core::{CoreConfig, FrameIn, FrameStep, Out as TrackerOut, TrackerCore};
use tracker::outbox::KeyframeMsg;
use tracker::testing::{frame_header, imu_msg};

const FRAMES: usize = 120;

/// The tracker core's keyframe messages of the synthetic loop's first frames, every one
/// acknowledged by `answer` as it is sent (the tracker keeps a keyframe until then).
fn keyframes_of_the_tracker(mut answer: impl FnMut(&KeyframeMsg) -> Vec<Feedback>) -> usize {
    let mut p = SimParams::new(Scenario::Loop);
    p.frames = Some(FRAMES);
    p.seed = 3;
    let world = SimWorld::new(p).expect("world");
    let cfg = CoreConfig {
        client: 0,
        no_vo: false,
        no_rs: false,
        window: 6,
        features: 1000,
        inline_mapping: true,
        lockstep_sync: false,
        spool: false,
        publish_features: false,
        mode: tracker::ClientMode::Mono,
        imu: Default::default(),
        calib: Default::default(),
        calib_log: false,
        readout: Default::default(),
        anchor: Default::default(),
    };
    let mut core = TrackerCore::new(cfg, Status::new("tracker:0"));
    let mut sent = 0;
    let mut take = |core: &mut TrackerCore, out: Vec<TrackerOut>| {
        for o in out {
            if let TrackerOut::Keyframe(m) = o {
                sent += 1;
                for f in answer(&m) {
                    core.on_feedback(&f);
                }
            }
        }
    };
    let (imu, mut next_imu) = (world.imu_samples(), 0);
    let c = world.calib().model;
    let mut img = vec![0u8; (c.width * c.height) as usize];
    for k in 0..world.n_frames() {
        let h = frame_header(&world, k);
        if let Some(need) = core.imu_needed_ns(&h, img.len()) {
            while core.imu_missing(need) && next_imu < imu.len() {
                core.on_imu(&imu_msg(next_imu as u64, &imu[next_imu]));
                next_imu += 1;
            }
        }
        world.render_frame_into(k, &mut img).expect("render");
        let frame = FrameIn {
            header: h,
            pixels: &img,
            recv_ns: 0,
            now_ns: 0,
        };
        let FrameStep::Tracked(mut t) = core.track(frame).expect("track") else {
            panic!("frame {k} not tracked");
        };
        take(&mut core, std::mem::take(&mut t.out));
        let out = core.publish_frame(t, 0);
        take(&mut core, out);
    }
    for kf in core.take_window() {
        let (_, out) = core.send_window_keyframe(&kf, 0);
        take(&mut core, out);
    }
    let mut imu_end = MsgMeta::new(0, 1, imu.len() as u64, 0);
    imu_end.flags = FLAG_END_OF_STREAM;
    core.on_imu(&ImuMsg {
        meta: imu_end,
        ..ImuMsg::default()
    });
    let mut eos = frame_header(&world, FRAMES);
    eos.meta.flags = FLAG_END_OF_STREAM;
    let out = core.end_of_stream(&eos, 0);
    take(&mut core, out);
    assert!(core.drained(), "the mapper acknowledged every keyframe");
    sent
}

/// A mapper core for one client, free-running (no lock-step synchronisation with a loop
/// closer), journaling to `journal` when given.
fn mapper(journal: Option<&std::path::Path>) -> (Mapper, Receiver<Report>) {
    let mut args = vec!["mapper".to_string(), "--clients=1".into()];
    if let Some(j) = journal {
        args.push(format!("--journal={}", j.display()));
    }
    let params = Params::parse_from(args);
    let (tx, rx) = crossbeam_channel::unbounded();
    let cfg = params.config().expect("default configuration");
    let mut m = Mapper::new(&params, &cfg, Status::new("mapper"), tx);
    if let Some(j) = journal {
        m.open_journal(j).expect("journal");
    }
    (m, rx)
}

/// What the mapper published.
#[derive(Default)]
struct Published {
    /// (session, keyframe id) of every plain acknowledgement.
    acks: Vec<(u32, u64)>,
    /// Feedback messages with a server pose.
    poses: usize,
    /// Keyframes forwarded to the loop closer.
    loop_keyframes: usize,
}

impl Published {
    fn take(&mut self, m: &mut Mapper) -> Vec<Feedback> {
        let mut back = Vec::new();
        for o in m.take_out() {
            match o {
                MapperOut::Feedback(f) if f.has_pose != 0 => {
                    self.poses += 1;
                    back.push(f);
                }
                MapperOut::Feedback(f) => {
                    assert_eq!(f.meta.flags & FLAG_HANDLED, 0, "free-running");
                    self.acks.push((f.acked_session_id, f.acked_keyframe_id));
                    back.push(f);
                }
                MapperOut::LoopKeyframe(h, records) => {
                    assert_eq!(h.n_keypoints as usize, records.len());
                    self.loop_keyframes += 1;
                }
            }
        }
        back
    }
}

fn map_size(m: &Mapper) -> (u64, u64, u64) {
    (m.counters.maps, m.counters.keyframes, m.counters.points)
}

/// Every keyframe of the tracker is journaled, acknowledged once and handled; the kept ones
/// are forwarded to the loop closer; the tracker gets server poses back.
#[test]
fn tracker_keyframes_through_the_mapper_core() {
    let (mut m, rx) = mapper(None);
    let mut out = Published::default();
    let mut msgs = Vec::new();
    let sent = keyframes_of_the_tracker(|k| {
        m.receive(0, &k.header, &k.payload()).expect("receive");
        msgs.push(k.key());
        // The outcomes arrive asynchronously: the feedback of earlier keyframes too.
        m.drain_outcomes(&rx).expect("outcomes");
        out.take(&mut m)
    });
    finish(&mut m, &rx, sent as u64, &mut out);
    let s = &m.status;
    eprintln!(
        "{sent} keyframes: kept {}, discarded {}, forwarded {}, server poses {}, map {:?}",
        m.counters.client(0).keyframes_kept,
        m.counters.client(0).keyframes_discarded,
        out.loop_keyframes,
        out.poses,
        map_size(&m)
    );
    assert!(sent >= 8, "{sent} keyframes");
    assert_eq!(out.acks, msgs, "each keyframe acknowledged once, in order");
    assert_eq!(m.counters.client(0).keyframes_applied, sent as u64);
    assert_eq!(m.counters.client(0).keyframes_duplicate, 0);
    assert_eq!(m.counters.maps, 1, "one map");
    let kept = m.counters.client(0).keyframes_kept;
    assert!(kept >= 4, "{kept} kept");
    assert!(m.counters.keyframes >= kept, "the map holds what was kept");
    assert!(m.counters.points > 100, "{} points", m.counters.points);
    assert_eq!(
        out.loop_keyframes as u64,
        m.counters.client(0).keyframes_forwarded
    );
    assert!(
        out.loop_keyframes as u64 >= kept - 1,
        "kept keyframes forwarded"
    );
    assert!(out.poses >= sent / 2, "{} server poses", out.poses);
    assert!(s.errors.is_empty(), "{:?}", s.errors);
}

fn handled(m: &Mapper) -> u64 {
    let c = m.counters.client(0);
    c.handled_kept
        + c.handled_discarded
        + c.handled_first
        + c.handled_map_created
        + c.handled_duplicate
}

/// Handles all keyframes waiting in the handlers.
fn finish(m: &mut Mapper, rx: &Receiver<Report>, n: u64, out: &mut Published) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while handled(m) < n {
        m.drain_outcomes(rx).expect("outcomes");
        out.take(m);
        assert!(Instant::now() < deadline, "handlers did not finish");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// A restarted mapper rebuilds the same map from its journal before taking keyframes, and
/// takes the re-sends of a tracker that never saw the acknowledgements as duplicates:
/// acknowledged again, not applied again.
#[test]
fn a_restarted_mapper_rebuilds_its_map_from_the_journal() {
    let dir = tempfile::tempdir().expect("tempdir");
    let journal = dir.path().join("mapper_journal.bin");
    let (mut m, rx) = mapper(Some(&journal));
    let mut out = Published::default();
    let mut msgs: Vec<KeyframeMsg> = Vec::new();
    let sent = keyframes_of_the_tracker(|k| {
        m.receive(0, &k.header, &k.payload()).expect("receive");
        msgs.push(k.clone());
        m.drain_outcomes(&rx).expect("outcomes");
        out.take(&mut m)
    }) as u64;
    finish(&mut m, &rx, sent, &mut out);
    let before = map_size(&m);
    drop(m);

    let (mut m2, rx2) = mapper(Some(&journal));
    let on_start = m2.status.values.get("journal_keyframes_on_start").copied();
    assert_eq!(on_start, Some(sent as f64), "every keyframe replayed");
    let mut out2 = Published::default();
    finish(&mut m2, &rx2, sent, &mut out2);
    assert_eq!(m2.counters.client(0).keyframes_replayed, sent);
    assert_eq!(map_size(&m2), before, "the same map rebuilt");
    assert_eq!(out2.acks.len(), 0, "a replay acknowledges nothing");

    let (first, rest) = msgs.split_at(1);
    for k in first.iter().chain(rest) {
        m2.receive(0, &k.header, &k.payload()).expect("receive");
    }
    m2.drain_outcomes(&rx2).expect("outcomes");
    out2.take(&mut m2);
    let keys: Vec<_> = msgs.iter().map(KeyframeMsg::key).collect();
    assert_eq!(out2.acks, keys, "each re-send acknowledged again");
    assert_eq!(m2.counters.client(0).keyframes_duplicate, sent);
    assert_eq!(m2.counters.client(0).keyframes_applied, 0);
    assert_eq!(map_size(&m2), before, "nothing applied twice");
    assert!(m2.status.errors.is_empty(), "{:?}", m2.status.errors);
}

/// A keyframe whose records disagree with its header is acknowledged (a re-send would be no
/// better), counted as an error naming the client, and not applied; the keyframes after it
/// are.
#[test]
fn a_malformed_keyframe_is_acknowledged_counted_and_skipped() {
    let (mut m, rx) = mapper(None);
    let mut out = Published::default();
    let mut n = 0u64;
    let sent = keyframes_of_the_tracker(|k| {
        n += 1;
        if n == 3 {
            let mut bad = k.header;
            bad.pose_ck.q = [f64::NAN; 4];
            m.receive(0, &bad, &k.payload()).expect("receive");
        } else {
            m.receive(0, &k.header, &k.payload()).expect("receive");
        }
        m.drain_outcomes(&rx).expect("outcomes");
        out.take(&mut m)
    }) as u64;
    finish(&mut m, &rx, sent - 1, &mut out);
    let s = &m.status;
    assert_eq!(out.acks.len() as u64, sent, "all acknowledged");
    assert_eq!(m.counters.client(0).keyframes_applied, sent - 1);
    let errs: Vec<_> = s
        .errors
        .iter()
        .filter(|e| e.kind == ErrorKind::BadKeyframe)
        .collect();
    assert_eq!(errs.len(), 1, "{:?}", s.errors);
    assert!(errs[0].detail.contains("client 0"), "{}", errs[0].detail);
    assert!(
        m.counters.keyframes >= 4,
        "the map grew past the bad keyframe"
    );
}
