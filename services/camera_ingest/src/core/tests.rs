//! The camera replay core fed in-process: restart and resume, real-time pacing after a
//! restart, lock-step acknowledgements (a consumer that restarts, one that never acks), a
//! corrupt image, the end of stream. Host times are plain numbers here.
use super::*;
use crate::service_name;

const MS: i64 = 1_000_000;

/// `n` frames at 10 Hz from t = 0.
fn frames(n: usize) -> Vec<datasets::FrameRecord> {
    (0..n)
        .map(|k| datasets::FrameRecord {
            t_ns: k as i64 * 100 * MS,
            path: format!("cam0/{k}.png").into(),
            exposure_ns: 5 * MS,
            readout_ns: 20 * MS,
            source: datasets::FrameSource::File,
        })
        .collect()
}

fn plan(mode: ReplayMode, frames: &[datasets::FrameRecord]) -> CameraReplayPlan<'_> {
    CameraReplayPlan {
        client: 3,
        mode,
        clock: ReplayClock {
            t0_mono_ns: 0,
            t_origin_ns: 0,
            rate: 1.0,
        },
        period_ns: 100 * MS,
        cfg: CameraIngestConfig::default(),
        template: FrameHeader {
            width: 4,
            height: 2,
            ..FrameHeader::default()
        },
        frames,
    }
}

/// A core on a first start.
fn fresh(mode: ReplayMode, frames: &[datasets::FrameRecord]) -> CameraReplayCore<'_> {
    CameraReplayCore::new(plan(mode, frames), Status::new(&service_name(3)))
}

fn ack(seq: u64) -> FrameAck {
    FrameAck {
        meta: MsgMeta::new(3, 1, seq, 0),
        frame_seq: seq,
        frame_t_ns: seq as i64 * 100 * MS,
    }
}

/// The status a killed predecessor left (written, read back, this start counted).
fn restarted(core: &mut CameraReplayCore) -> Status {
    let text = serde_json::to_string(core.status()).unwrap();
    let mut back: Status = serde_json::from_str(&text).unwrap();
    back.starts += 1;
    back
}

/// Lock-step with a consumer that acknowledges every frame at once: publishes `n` frames
/// from where `core` is, returning their indices.
fn lockstep_acked(core: &mut CameraReplayCore, n: usize, now_ns: i64) -> Vec<usize> {
    let mut sent = Vec::new();
    while sent.len() < n {
        match core.step(now_ns) {
            CameraStep::Publish { index, header } => {
                assert_eq!(header.meta.flags & FLAG_RESEND, 0, "a first send");
                assert_eq!(header.dataset_index, index as u64);
                core.on_sent(now_ns);
                core.on_ack(&ack(index as u64));
                sent.push(index);
            }
            CameraStep::Continue => {}
            other => panic!("unexpected {other:?}"),
        }
    }
    sent
}

/// A restart resumes the position and the counters its predecessor wrote; the messages of
/// the new start carry a new session id.
#[test]
fn a_restart_resumes_position_and_counters() {
    let fr = frames(10);
    let mut first = fresh(ReplayMode::Lockstep, &fr);
    assert_eq!(lockstep_acked(&mut first, 4, 0), [0, 1, 2, 3]);
    // Frame 4 published, then the process dies before its acknowledgement.
    assert!(matches!(first.step(0), CameraStep::Continue));
    assert!(matches!(
        first.step(0),
        CameraStep::Publish { index: 4, .. }
    ));
    first.on_sent(0);
    let left = restarted(&mut first);
    let json = serde_json::to_value(&left).unwrap();
    assert_eq!(json["resume"]["state"]["next_index"], 4);
    assert_eq!(json["counters"]["frames_published"], 5);
    assert_eq!(json["values"]["frames_total"], 10.0);

    let mut second = CameraReplayCore::new(plan(ReplayMode::Lockstep, &fr), left);
    assert_eq!((second.next_index(), second.session_id()), (4, 2));
    match second.step(0) {
        CameraStep::Publish { index, header } => {
            assert_eq!((index, header.meta.session_id, header.meta.seq), (4, 2, 4));
            assert_eq!(header.t_mid_ns, 400 * MS);
            assert_eq!((header.readout_ns, header.width), (20 * MS, 4));
        }
        other => panic!("unexpected {other:?}"),
    }
    second.on_sent(0);
    second.on_ack(&ack(4));
    assert_eq!(lockstep_acked(&mut second, 5, 0), [5, 6, 7, 8, 9]);
    assert!(matches!(second.step(0), CameraStep::Continue));
    let c = second.counters();
    // Frame 4 twice (once per life), as the counter's doc says.
    assert_eq!((c.frames_published, c.frames_offered), (11, 10));
    assert!(second.status_mut().error_counts.is_empty());
}

/// A resume state of another format: counted, named, and the replay starts over (the
/// counters carry on).
#[test]
fn a_resume_state_of_another_version_starts_afresh() {
    let fr = frames(10);
    let mut first = fresh(ReplayMode::Lockstep, &fr);
    lockstep_acked(&mut first, 3, 0);
    let mut left = restarted(&mut first);
    left.set_resume(RESUME_VERSION + 1, &CameraResume { next_index: 3 });
    let mut second = CameraReplayCore::new(plan(ReplayMode::Lockstep, &fr), left);
    assert_eq!(second.next_index(), 0);
    assert_eq!(second.counters().frames_published, 3);
    let s = second.status_mut();
    assert_eq!(s.errors_of(ErrorKind::ResumeState), 1);
    assert!(s.errors[0].detail.contains("starting afresh"));
    assert!(matches!(
        second.step(0),
        CameraStep::Publish { index: 0, .. }
    ));
}

/// Real time, restarted 1 s into the stream: the frames due more than 250 ms ago (0..=7) are
/// skipped and counted, 8..=10 go out at once, 11 is waited for.
#[test]
fn a_real_time_restart_skips_the_frames_due_long_ago() {
    let fr = frames(20);
    let mut status = Status::new(&service_name(3));
    status.starts = 2;
    let mut core = CameraReplayCore::new(plan(ReplayMode::Realtime, &fr), status);
    let now = 1000 * MS;
    let mut published = Vec::new();
    loop {
        match core.step(now) {
            CameraStep::Continue => {}
            CameraStep::Publish { index, .. } => {
                core.on_sent(now);
                published.push(index);
            }
            CameraStep::Wait { for_ns } => {
                assert_eq!(for_ns, 100 * MS as u64, "frame 11 is due in 100 ms");
                break;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(published, [8, 9, 10]);
    let c = core.counters().clone();
    assert_eq!((c.frames_skipped_late, c.frames_published), (8, 3));
    assert_eq!((c.frames_offered, core.next_index()), (11, 11));
    // Waited for (even if the wait overran): published, not skipped.
    assert!(matches!(
        core.step(now + 400 * MS),
        CameraStep::Publish { index: 11, .. }
    ));
}

/// Lock-step, the consumer restarts while frame 2 is out: frame 2 is re-sent (flagged) every
/// second until the new consumer acknowledges it; the re-sends are counted.
#[test]
fn lockstep_resends_to_a_restarted_consumer() {
    let fr = frames(5);
    let mut core = fresh(ReplayMode::Lockstep, &fr);
    lockstep_acked(&mut core, 2, 0);
    assert!(matches!(core.step(0), CameraStep::Continue));
    assert!(matches!(core.step(0), CameraStep::Publish { index: 2, .. }));
    core.on_sent(0);
    let mut resends = Vec::new();
    for t_ms in (0..=2500).step_by(50) {
        match core.step(t_ms * MS) {
            CameraStep::Wait { for_ns } => assert_eq!(for_ns, ACK_POLL_NS),
            CameraStep::Publish { index, header } => {
                assert_eq!(index, 2);
                assert_ne!(header.meta.flags & FLAG_RESEND, 0);
                core.on_sent(t_ms * MS);
                resends.push(t_ms);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    // Re-sent when more than 1000 ms passed since the last send.
    assert_eq!(resends, [1050, 2100]);
    // An ack of an older frame does not count; the one of frame 2 does.
    core.on_ack(&ack(1));
    assert!(matches!(core.step(2550 * MS), CameraStep::Wait { .. }));
    core.on_ack(&ack(2));
    assert!(matches!(core.step(2600 * MS), CameraStep::Continue));
    assert_eq!(core.next_index(), 3);
    let c = core.counters();
    assert_eq!(
        (c.frames_resent, c.frames_unacked, c.frames_published),
        (2, 0, 3)
    );
}

/// Lock-step, a consumer that never acknowledges: after the ack timeout the frame is counted
/// as unacked (an `ack_timeout` error naming it) and the replay goes on.
#[test]
fn lockstep_gives_up_after_the_ack_timeout() {
    let fr = frames(3);
    let mut p = plan(ReplayMode::Lockstep, &fr);
    p.cfg.ack_timeout_ms = 3000;
    let mut core = CameraReplayCore::new(p, Status::new(&service_name(3)));
    let mut events = Vec::new();
    let mut t = 0;
    while core.next_index() < 2 {
        match core.step(t) {
            CameraStep::Publish { index, .. } => {
                core.on_sent(t);
                events.push((index, t / MS));
            }
            CameraStep::Wait { .. } => t += 100 * MS,
            CameraStep::Continue => {}
            other => panic!("unexpected {other:?}"),
        }
    }
    // Frame 0 at 0, re-sent at 1100 and 2200 ms; given up at 3100 ms; frame 1 alike.
    let expect = [
        (0, 0),
        (0, 1100),
        (0, 2200),
        (1, 3100),
        (1, 4200),
        (1, 5300),
    ];
    assert_eq!(events, expect);
    let c = core.counters();
    assert_eq!(
        (c.frames_unacked, c.frames_resent, c.frames_offered),
        (2, 0, 2)
    );
    let s = core.status_mut();
    assert_eq!(s.errors_of(ErrorKind::AckTimeout), 2);
    assert!(s.errors[1].detail.contains("frame 1 within 3000 ms"));
}

/// A corrupt image: counted and named, not published, and the replay goes on. A re-send of
/// it that fails (the file changed since) is fatal.
#[test]
fn a_corrupt_image_is_counted_and_skipped() {
    let fr = frames(3);
    let mut core = fresh(ReplayMode::Realtime, &fr);
    let now = 150 * MS;
    assert!(matches!(
        core.step(now),
        CameraStep::Publish { index: 0, .. }
    ));
    core.on_sent(now);
    assert!(matches!(
        core.step(now),
        CameraStep::Publish { index: 1, .. }
    ));
    core.on_corrupt("cam0/1.png: bad PNG".into()).unwrap();
    assert!(matches!(core.step(now), CameraStep::Wait { .. }));
    let c = core.counters().clone();
    assert_eq!((c.frames_published, c.frames_offered), (1, 2));
    let s = core.status_mut();
    assert_eq!(s.errors_of(ErrorKind::CorruptImage), 1);
    assert!(s.errors[0].detail.contains("cam0/1.png"));

    let mut lock = fresh(ReplayMode::Lockstep, &fr);
    assert!(matches!(lock.step(0), CameraStep::Publish { .. }));
    lock.on_sent(0);
    assert!(matches!(lock.step(1001 * MS), CameraStep::Publish { .. }));
    assert!(lock.on_corrupt("gone".into()).is_err());
}

/// The end of stream (sequence number: the frame count) is re-sent every 250 ms until it is
/// acknowledged; the status is then finished.
#[test]
fn the_end_of_stream_is_resent_until_acknowledged() {
    let fr = frames(2);
    let mut core = fresh(ReplayMode::Lockstep, &fr);
    lockstep_acked(&mut core, 2, 0);
    assert!(matches!(core.step(0), CameraStep::Continue));
    let mut eos_at = Vec::new();
    let mut t = 0;
    loop {
        match core.step(t) {
            CameraStep::PublishEndOfStream { header } => {
                assert!(header.meta.is_end_of_stream());
                assert_eq!((header.meta.seq, header.meta.session_id), (2, 1));
                core.on_sent(t);
                eos_at.push(t / MS);
            }
            CameraStep::Wait { .. } => t += 100 * MS,
            CameraStep::Done => break,
            other => panic!("unexpected {other:?}"),
        }
        if t == 700 * MS {
            // A frame's late ack does not end the wait: the end of stream's does.
            core.on_ack(&ack(1));
        }
        if t == 900 * MS {
            core.on_ack(&ack(2));
        }
    }
    assert_eq!(eos_at, [0, 300, 600]);
    assert_eq!(t, 900 * MS);
    let s = core.into_status();
    assert!(s.finished);
    assert_eq!(s.counters["frames_published"], 2);
}

/// A consumer that never takes the end of stream: the re-sends stop at the ack timeout.
#[test]
fn the_end_of_stream_wait_is_bounded() {
    let fr = frames(1);
    let mut p = plan(ReplayMode::Realtime, &fr);
    p.cfg.ack_timeout_ms = 1000;
    let mut core = CameraReplayCore::new(p, Status::new(&service_name(3)));
    let (mut t, mut eos) = (0, 0);
    loop {
        match core.step(t) {
            CameraStep::Publish { .. } | CameraStep::PublishEndOfStream { .. } => {
                core.on_sent(t);
                eos += 1;
            }
            CameraStep::Wait { .. } => t += 50 * MS,
            CameraStep::Done => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    // The frame, then the end of stream at 0, 300, 600, 900 ms; over after 1000 ms.
    assert_eq!((eos, t), (5, 1050 * MS));
    assert_eq!(core.counters().frames_unacked, 0, "not a frame");
    assert!(core.into_status().finished);
}
