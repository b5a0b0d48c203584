//! The loop closer's core fed in-process, without iceoryx2: the resynchronisation protocol of
//! a restarted loop closer (batches asked for until the mapper's end marker, a stalled
//! request repeated), the lock-step "done" marker behind every live keyframe (also a
//! malformed one), and messages of another schema refused. Detection itself is tested in
//! `slam_core::loop_closing`; the process wiring in `tests/loop_closer.rs`.
use clap::Parser;
use loop_closer::{Closer, LoopCloserCore, Out, Params};
use shm_schema::{
    Intrinsics, LoopKeyframeHeader, LoopKeypointRecord, MsgMeta, ResyncRequest, CORRECTION_DONE,
    FLAG_END_OF_STREAM, FLAG_RESYNC,
};
use shoal_runtime::{ErrorKind, Status};

const S: i64 = 1_000_000_000;

fn params(lockstep: bool) -> Params {
    let mode = if lockstep { "lockstep" } else { "realtime" };
    Params::parse_from(["loop_closer", "--mode", mode])
}

/// A core as started for the `starts`-th time (1: the first start of a run).
fn core(lockstep: bool, starts: u64) -> (LoopCloserCore, Vec<Out>) {
    let p = params(lockstep);
    let cfg = p.config().expect("default configuration");
    let vocabulary = loop_closer::vocabulary(&cfg).expect("shipped vocabulary");
    let mut status = Status::new("loop_closer");
    status.starts = starts;
    LoopCloserCore::new(Closer::new(vocabulary, cfg.method), &p, &cfg, status, 0)
}

/// A plausible loop keyframe of client `c`: 60 keypoints with pseudo-random descriptors,
/// half of them with a point 2-6 m in front.
fn keyframe(
    c: u32,
    seq: u64,
    kf: u64,
    flags: u32,
) -> (LoopKeyframeHeader, Vec<LoopKeypointRecord>) {
    let mut state = kf.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let records: Vec<_> = (0..60u32)
        .map(|i| {
            let r = next();
            let mut descriptor = [0u8; 32];
            for (j, b) in descriptor.iter_mut().enumerate() {
                *b = (next() >> (j % 8)) as u8;
            }
            LoopKeypointRecord {
                u: (r % 700) as f32 + 20.0,
                v: ((r >> 16) % 440) as f32 + 20.0,
                angle: (r >> 32) as f32 % 360.0,
                response: 10.0,
                octave: i % 4,
                has_point: i % 2,
                point_id: kf * 1000 + u64::from(i),
                p_k: [0.1 * f64::from(i % 7), -0.2, 2.0 + f64::from(i % 5)],
                descriptor,
            }
        })
        .collect();
    let mut meta = MsgMeta::new(c, 0, seq, 0);
    meta.flags = flags;
    let h = LoopKeyframeHeader {
        meta,
        map_id: u64::from(c) << 32,
        kf_id: kf,
        client_kf_id: kf,
        t_ns: kf as i64 * S / 10,
        intrinsics: Intrinsics {
            pinhole: [458.0, 457.0, 367.0, 248.0],
            distortion: [0.0; 5],
        },
        width: 752,
        height: 480,
        n_keypoints: records.len() as u32,
        ..LoopKeyframeHeader::default()
    };
    (h, records)
}

fn requests(out: &[Out]) -> Vec<(u64, u32)> {
    out.iter()
        .filter_map(|o| match o {
            Out::Resync(ResyncRequest { next, max, .. }) => Some((*next, *max)),
            Out::Correction(_) => None,
        })
        .collect()
}

/// A restarted loop closer rebuilds its database from the mapper's snapshot: it asks for
/// batches until the end marker, repeats a request that made no progress for 2 s, and
/// ignores resync keyframes after the end.
#[test]
fn a_restarted_loop_closer_resynchronises_in_batches() {
    let (mut lc, out) = core(false, 2);
    assert_eq!(requests(&out), vec![(0, 32)], "asks from the start");
    let mut asked = vec![];
    for k in 0..70u64 {
        let (h, r) = keyframe(0, k, 100 + k, FLAG_RESYNC);
        let out = lc.on_keyframe(&h, &r, S);
        asked.extend(requests(&out));
        assert!(out.iter().all(|o| matches!(o, Out::Resync(_))));
    }
    assert_eq!(
        asked,
        vec![(32, 32), (64, 32)],
        "one request per full batch"
    );
    assert_eq!(requests(&lc.on_tick(2 * S)), vec![], "progress within 2 s");
    assert_eq!(
        requests(&lc.on_tick(4 * S)),
        vec![(70, 32)],
        "a stalled batch asked again from where it is"
    );
    let (mut end, _) = keyframe(0, 70, 0, FLAG_RESYNC | FLAG_END_OF_STREAM);
    end.n_keypoints = 0;
    assert!(lc.on_keyframe(&end, &[], 5 * S).is_empty());
    assert_eq!(lc.counters.resync_keyframes, 70);
    assert!(lc.on_tick(10 * S).is_empty(), "done: nothing more asked");
    let (h, r) = keyframe(0, 71, 999, FLAG_RESYNC);
    assert!(
        lc.on_keyframe(&h, &r, 10 * S).is_empty(),
        "a late batch is ignored"
    );
    // The database holds the snapshot: a live keyframe is searched against 70 others.
    let (h, r) = keyframe(0, 0, 200, 0);
    lc.on_keyframe(&h, &r, 11 * S);
    assert_eq!(lc.counters.database_keyframes, 71);
    assert!(lc.status.errors.is_empty(), "{:?}", lc.status.errors);
}

/// The first start of a lock-step run asks for no snapshot (the maps are empty), and every
/// live keyframe, even one that cannot be decoded, is followed by its "done" marker, so the
/// mapper's lock-step wait always ends.
#[test]
fn lockstep_marks_every_live_keyframe_done() {
    let (mut lc, out) = core(true, 1);
    assert!(out.is_empty(), "no resync on the first lock-step start");
    for k in 0..5u64 {
        let (mut h, r) = keyframe(1, 40 + k, 500 + k, 0);
        if k == 2 {
            h.n_keypoints += 1; // disagrees with its payload
        }
        let out = lc.on_keyframe(&h, &r, S);
        let Some(Out::Correction(done)) = out.last() else {
            panic!("keyframe {k}: no done marker in {out:?}");
        };
        assert_eq!(done.header.kind, CORRECTION_DONE);
        assert_eq!(
            done.header.meta.seq,
            40 + k,
            "names the loop keyframe message"
        );
        assert_eq!(done.header.query_kf, 500 + k);
    }
    assert_eq!(lc.counters.client(1).keyframes_received, 5);
    assert_eq!(
        lc.counters.database_keyframes, 4,
        "the malformed one left out"
    );
    assert_eq!(lc.status.errors.len(), 1, "{:?}", lc.status.errors);
    let e = &lc.status.errors[0];
    assert_eq!(e.kind, ErrorKind::BadKeyframe);
    assert!(
        e.detail.contains("0x1f6"),
        "names the keyframe: {}",
        e.detail
    );
}

/// A message of another schema version is refused with a named error and no output (not
/// even a done marker: its sequence number cannot be trusted).
#[test]
fn a_foreign_schema_keyframe_is_refused() {
    let (mut lc, _) = core(true, 1);
    let (mut h, r) = keyframe(0, 0, 7, 0);
    h.meta.schema_version += 1;
    assert!(lc.on_keyframe(&h, &r, S).is_empty());
    assert_eq!(lc.counters.client(0).keyframes_received, 0);
    assert_eq!(lc.status.errors.len(), 1);
    assert_eq!(lc.status.errors[0].kind, ErrorKind::SchemaVersion);
}
