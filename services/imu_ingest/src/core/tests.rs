//! The IMU replay core fed in-process: restart and resume, real-time pacing after a
//! restart, the lock-step horizon over a gap in the samples, the reader's skipped lines, the
//! end of stream. Host times are plain numbers here.
use super::*;
use crate::service_name;
use shoal_runtime::ErrorKind;

const MS: i64 = 1_000_000;

fn sample(t_ns: i64) -> datasets::ImuSample {
    datasets::ImuSample {
        t_ns,
        gyro: [0.1, 0.2, 0.3],
        accel: [0.0, 0.0, 9.81],
    }
}

/// Samples every `step_ms` ms in `[from_ms, to_ms]`.
fn samples(from_ms: i64, to_ms: i64, step_ms: usize) -> Vec<datasets::ImuSample> {
    (from_ms..=to_ms)
        .step_by(step_ms)
        .map(|t| sample(t * MS))
        .collect()
}

fn plan(mode: ReplayMode, samples: &[datasets::ImuSample]) -> ImuReplayPlan<'_> {
    ImuReplayPlan {
        client: 1,
        mode,
        clock: ReplayClock {
            t0_mono_ns: 0,
            t_origin_ns: 0,
            rate: 1.0,
        },
        lookahead_ns: 100 * MS,
        first_frame_t_ns: Some(0),
        samples,
    }
}

/// A core on a first start.
fn fresh(mode: ReplayMode, samples: &[datasets::ImuSample]) -> ImuReplayCore<'_> {
    ImuReplayCore::new(plan(mode, samples), Status::new("imu"))
}

fn ack(frame_t_ns: i64) -> FrameAck {
    FrameAck {
        meta: MsgMeta::new(1, 1, 0, 0),
        frame_seq: 0,
        frame_t_ns,
    }
}

/// Publishes what the core lets out at `now_ns` until it waits or ends: the sample times
/// (ms), and the wait asked for (ns; `None`: the replay is done).
fn run_at(core: &mut ImuReplayCore, now_ns: i64) -> (Vec<i64>, Option<u64>) {
    let mut out = Vec::new();
    loop {
        match core.step(now_ns) {
            ImuStep::Publish(m) => {
                assert_eq!(m.meta.seq, core.next_index() as u64);
                out.push(m.t_ns / MS);
                core.on_sent();
            }
            ImuStep::Continue | ImuStep::PublishEndOfStream(_) => {}
            ImuStep::Wait { for_ns } => return (out, Some(for_ns)),
            ImuStep::Done => return (out, None),
        }
    }
}

/// The status a killed predecessor left (written, read back, this start counted).
fn restarted(core: &mut ImuReplayCore) -> Status {
    let text = serde_json::to_string(core.status()).unwrap();
    let mut back: Status = serde_json::from_str(&text).unwrap();
    back.starts += 1;
    back
}

/// A restart (lock-step) resumes the position and counters its predecessor wrote, under
/// their names in the status file, and publishes from there with a new session id.
#[test]
fn a_restart_resumes_position_and_counters() {
    let s = samples(0, 300, 10);
    let mut first = fresh(ReplayMode::Lockstep, &s);
    assert_eq!(
        run_at(&mut first, 0),
        ((0..=10).map(|k| k * 10).collect(), Some(ACK_POLL_NS))
    );
    let left = restarted(&mut first);
    let json = serde_json::to_value(&left).unwrap();
    assert_eq!(json["counters"]["imu_samples_published"], 11);
    assert_eq!(json["resume"]["version"], RESUME_VERSION);
    assert_eq!(json["resume"]["state"]["next_index"], 11);
    assert!(left.values.is_empty(), "no position among the values");

    let mut second = ImuReplayCore::new(plan(ReplayMode::Lockstep, &s), left);
    assert_eq!(second.next_index(), 11);
    second.on_ack(&ack(100 * MS));
    match second.step(0) {
        ImuStep::Publish(m) => {
            assert_eq!((m.meta.seq, m.meta.session_id, m.t_ns), (11, 2, 110 * MS))
        }
        other => panic!("unexpected {other:?}"),
    }
    second.on_sent();
    assert_eq!(
        run_at(&mut second, 0).0,
        [120, 130, 140, 150, 160, 170, 180, 190, 200]
    );
    let c = second.counters();
    assert_eq!(
        (c.imu_samples_published, c.imu_samples_skipped_late),
        (21, 0)
    );
    assert!(second.status_mut().error_counts.is_empty());
}

/// A resume state of another format: counted, named, and the replay starts over (the
/// counters carry on). No resume section (a first start): from the first sample, no error.
#[test]
fn a_resume_state_of_another_version_starts_afresh() {
    let s = samples(0, 100, 10);
    let mut first = fresh(ReplayMode::Lockstep, &s);
    run_at(&mut first, 0);
    assert_eq!(first.next_index(), 11);
    let mut left = restarted(&mut first);
    left.set_resume(RESUME_VERSION + 1, &ImuResume { next_index: 11 });
    let mut second = ImuReplayCore::new(plan(ReplayMode::Lockstep, &s), left);
    assert_eq!(
        (second.next_index(), second.counters().imu_samples_published),
        (0, 11)
    );
    assert_eq!(second.status_mut().errors_of(ErrorKind::ResumeState), 1);
    assert!(first.status_mut().error_counts.is_empty());
}

/// Real time, 1 s into the stream: a restarted ingest skips the samples due more than
/// 50 ms ago and counts them; a first start publishes them all (no catching up to skip).
#[test]
fn a_real_time_restart_skips_the_samples_due_long_ago() {
    let s = samples(0, 2000, 5);
    let mut status = Status::new(&service_name(1));
    status.starts = 2;
    let mut core = ImuReplayCore::new(plan(ReplayMode::Realtime, &s), status);
    let (out, wait) = run_at(&mut core, 1000 * MS);
    // Due at 950 ms is not late by more than 50 ms: 190 (950 ms) ..= 200 (1000 ms) go out.
    assert_eq!(out, (950..=1000).step_by(5).collect::<Vec<_>>());
    assert_eq!(wait, Some(5 * MS as u64), "sample 201 is due in 5 ms");
    let c = core.counters().clone();
    assert_eq!(
        (c.imu_samples_skipped_late, c.imu_samples_published),
        (190, 11)
    );
    // Waited for: published even if the wait overran.
    assert!(matches!(core.step(1200 * MS), ImuStep::Publish(m) if m.t_ns == 1005 * MS));

    let mut fresh = fresh(ReplayMode::Realtime, &s);
    assert_eq!(run_at(&mut fresh, 1000 * MS).0.len(), 201);
    assert_eq!(fresh.counters().imu_samples_skipped_late, 0);
}

/// Lock-step: samples up to the last acknowledged frame + 100 ms. Over a gap in the samples
/// (150 ms to 400 ms) the ingest waits for the acknowledgement that moves the horizon past
/// it; an older or foreign acknowledgement does not move it.
#[test]
fn lockstep_publishes_up_to_the_horizon_over_a_gap() {
    let mut s = samples(0, 150, 10);
    s.extend(samples(400, 450, 10));
    let mut core = fresh(ReplayMode::Lockstep, &s);
    let (out, wait) = run_at(&mut core, 0);
    assert_eq!(
        (out.len(), out.last(), wait),
        (11, Some(&100), Some(ACK_POLL_NS))
    );
    core.on_ack(&ack(100 * MS));
    assert_eq!(run_at(&mut core, 0).0, [110, 120, 130, 140, 150]);
    core.on_ack(&ack(200 * MS));
    core.on_ack(&ack(50 * MS));
    let mut foreign = ack(400 * MS);
    foreign.meta.schema_version += 1;
    core.on_ack(&foreign);
    assert_eq!(core.horizon_ns(), 300 * MS);
    assert_eq!(run_at(&mut core, 0), (vec![], Some(ACK_POLL_NS)));
    core.on_ack(&ack(310 * MS));
    assert_eq!(run_at(&mut core, 0).0, [400, 410]);
    assert_eq!(core.counters().imu_samples_published, 18);
}

/// A restarted tracker's replay request (lock-step): the samples from the one at or before
/// the asked time are published again, with their own sequence numbers, then the replay
/// goes on with the acknowledgements; the end of stream follows again. In real time a
/// request changes nothing.
#[test]
fn a_replay_request_publishes_the_samples_again_from_the_asked_time() {
    let s = samples(0, 300, 10);
    let mut core = fresh(ReplayMode::Lockstep, &s);
    core.on_ack(&ack(200 * MS));
    assert_eq!(run_at(&mut core, 0).0.len(), 31);
    let replay = |t_ns| {
        let mut a = ack(t_ns);
        a.meta.flags |= FLAG_IMU_REPLAY;
        a
    };
    core.on_ack(&replay(255 * MS));
    assert_eq!(
        core.horizon_ns(),
        300 * MS,
        "a replay request moves no horizon"
    );
    assert_eq!(run_at(&mut core, 0).0, [250, 260, 270, 280, 290, 300]);
    core.on_ack(&replay(400 * MS));
    assert_eq!(
        run_at(&mut core, 0),
        (vec![300], None),
        "the sample before the time"
    );
    core.on_ack(&replay(290 * MS));
    let mut eos = 0;
    loop {
        match core.step(0) {
            ImuStep::Publish(m) => {
                assert_eq!(m.meta.seq, 29 + eos);
                eos += 1;
                core.on_sent();
            }
            ImuStep::PublishEndOfStream(_) => eos += 100,
            ImuStep::Done => break,
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(eos, 102, "samples 29 and 30, then the end of stream again");
    let c = core.counters();
    assert_eq!((c.imu_replays, c.imu_samples_replayed), (3, 6 + 1 + 2));
    assert_eq!(c.imu_samples_published, 31 + 9);
    let mut rt = fresh(ReplayMode::Realtime, &s);
    rt.on_ack(&replay(0));
    assert_eq!(rt.counters().imu_replays, 0);
    assert_eq!(rt.next_index(), 0);
}

/// A dataset without frames has no acknowledgements to wait for: real-time pacing also in
/// lock-step mode.
#[test]
fn without_frames_lockstep_paces_in_real_time() {
    let s = samples(50, 100, 10);
    let mut p = plan(ReplayMode::Lockstep, &s);
    p.first_frame_t_ns = None;
    let mut core = ImuReplayCore::new(p, Status::new("imu"));
    assert_eq!(run_at(&mut core, 0), (vec![], Some(50 * MS as u64)));
    assert_eq!(
        run_at(&mut core, 75 * MS),
        (vec![50, 60, 70], Some(5 * MS as u64))
    );
}

/// The lines the reader skipped (non-monotonic, malformed) are reported once, on a first
/// start, and only those of the IMU files; the samples reach the core in time order.
#[test]
fn skipped_imu_lines_are_reported_on_the_first_start() {
    let issue = |path: &str, line, kind| datasets::InputIssue {
        path: path.into(),
        line,
        kind,
        detail: "skipped".into(),
    };
    let issues = [
        issue("mav0/imu0/data.csv", 7, datasets::IssueKind::NonMonotonic),
        issue("mav0/imu0/data.csv", 9, datasets::IssueKind::MalformedLine),
        issue("mav0/cam0/data.csv", 3, datasets::IssueKind::MissingImage),
    ];
    let s = samples(0, 50, 10);
    let mut core = fresh(ReplayMode::Lockstep, &s);
    shoal_runtime::report_input_issues(core.status_mut(), &issues, true);
    let st = core.status_mut();
    assert_eq!(st.errors_of(ErrorKind::NonMonotonic), 1);
    assert_eq!(st.errors_of(ErrorKind::MalformedLine), 1);
    assert_eq!(
        st.errors_of(ErrorKind::MissingImage),
        0,
        "the camera ingest's"
    );
    assert!(st.errors[0].detail.starts_with("mav0/imu0/data.csv:7"));
    let mut again = ImuReplayCore::new(plan(ReplayMode::Lockstep, &s), restarted(&mut core));
    shoal_runtime::report_input_issues(again.status_mut(), &issues, true);
    assert_eq!(
        again.status_mut().errors_of(ErrorKind::NonMonotonic),
        1,
        "not twice"
    );
}

/// After the last sample: one end of stream (sequence number: the sample count), then done;
/// the status is finished.
#[test]
fn the_end_of_stream_follows_the_last_sample_once() {
    let s = samples(0, 40, 10);
    let mut core = fresh(ReplayMode::Lockstep, &s);
    for _ in 0..5 {
        assert!(matches!(core.step(0), ImuStep::Publish(_)));
        core.on_sent();
    }
    match core.step(0) {
        ImuStep::PublishEndOfStream(m) => {
            assert!(m.meta.is_end_of_stream());
            assert_eq!(m.meta.seq, 5);
        }
        other => panic!("unexpected {other:?}"),
    }
    assert_eq!(core.step(0), ImuStep::Done);
    let st = core.into_status();
    assert!(st.finished);
    assert_eq!(st.counters["imu_samples_published"], 5);
}
