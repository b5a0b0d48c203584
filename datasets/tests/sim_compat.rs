//! The EuRoC reader on a folder written by our own generator (`datasets::sim`), with a
//! camera-IMU offset t_d and a rolling shutter: frame stamps, readout and the two ground
//! truths (camera TUM file vs. body CSV through T_BS) must agree.

use datasets::sim::{generate, Scenario, SimParams};
use datasets::trajectory::interpolate_at;
use datasets::{euroc, open};

#[test]
fn generator_output_reads_back_consistently() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut params = SimParams::new(Scenario::FastRs);
    params.frames = Some(6);
    params.time_offset_ms = 3.0;
    generate(&params, tmp.path()).expect("generate");
    // The generator may write into an agent sub-folder.
    let root = if tmp.path().join("mav0").is_dir() {
        tmp.path().to_path_buf()
    } else {
        tmp.path().join("agent0")
    };
    let ds = open(&root).expect("open");
    assert!(ds.issues.is_empty(), "{:#?}", ds.issues);
    assert_eq!(ds.frames.len(), 6);
    assert_eq!(ds.camera.time_offset_ns, 3_000_000);
    assert_eq!(ds.camera.readout_ns, params.readout_ns());
    assert!(ds.camera.readout_ns > 0);
    assert!(!ds.imu.is_empty());
    let gt = ds.ground_truth.as_ref().expect("gt");
    assert_eq!(gt.len(), 6);
    // Camera TUM ground truth (shifted by t_d) vs body ground truth mapped by T_BS, both at the
    // corrected frame time.
    let mut issues = Vec::new();
    let body = euroc::read_gt_csv(
        &root.join("mav0/state_groundtruth_estimate0/data.csv"),
        &mut issues,
    )
    .expect("gt csv");
    for (f, g) in ds.frames.iter().zip(gt) {
        assert_eq!(f.t_ns, g.t_ns);
        let Some(b) = interpolate_at(&body, f.t_ns) else {
            continue;
        };
        let cam = b * ds.camera.t_bs;
        let d = (cam.translation.vector - g.pose.translation.vector).norm();
        assert!(
            d < 2e-3,
            "camera gt differs from body gt by {d} m at {}",
            f.t_ns
        );
    }
}

/// The full ground-truth state (velocity, biases) written by the generator reads back
/// exactly with `euroc::read_gt_states_csv`.
#[test]
fn ground_truth_states_read_back() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut params = SimParams::new(Scenario::Loop);
    params.frames = Some(2);
    params.pixel_noise_sigma = 0.0;
    generate(&params, tmp.path()).expect("generate");
    let world = datasets::sim::SimWorld::new(params).expect("world");
    let mut issues = Vec::new();
    let csv = tmp.path().join("mav0/state_groundtruth_estimate0/data.csv");
    let states = euroc::read_gt_states_csv(&csv, &mut issues).expect("read");
    assert!(issues.is_empty(), "{issues:?}");
    let truth = world.ground_truth_states();
    assert_eq!(states.len(), truth.len());
    for (a, b) in states.iter().zip(truth) {
        assert_eq!(
            (a.t_ns, a.p_wb, a.v_w, a.biases),
            (b.t_ns, b.p_wb, b.v_w, b.biases)
        );
        assert!(a.q_wb.angle_to(&b.q_wb) < 1e-12);
    }
    // A short line is skipped and recorded.
    std::fs::write(&csv, "#t\n1,2,3\n").expect("write");
    let states = euroc::read_gt_states_csv(&csv, &mut issues).expect("read");
    assert!(
        states.is_empty()
            && issues.len() == 1
            && issues[0].kind == datasets::IssueKind::MalformedLine
    );
}
