//! The visual-inertial client through the whole pipeline (issue 17): camera and IMU replayed
//! through shared memory, the tracker in `vio` mode, the launcher's recorder re-expressing
//! the poses published before the inertial initialisation's world move. Checked against the
//! synthetic ground truth: the trajectory is metric (a Sim(3) alignment finds scale ≈ 1),
//! gravity-aligned (the 4-DoF alignment's tilt error is small) and complete; `auto` picks
//! `vio` on a dataset with an IMU and extrinsics, `mono` is the chapter-3 client.
mod common;

use common::*;

/// 12 s of the `drone` scenario (aggressive 6-DoF motion, global shutter), lock-step.
#[test]
fn drone_vio_is_metric_and_gravity_aligned() {
    let tmp = tempdir();
    let ds = synthetic(tmp.path(), "drone", 240, None);
    let out = tmp.path().join("vio");
    let res = run_pipeline(
        &[&ds[0]],
        &out,
        "vio_drone",
        &["--lockstep", "--mode", "auto"],
    );
    assert!(res.status.success());
    let rep = report(&out);
    let c = &rep["clients"][0];
    assert_eq!(c["client_mode"], "vio", "{}", c["client_mode_reason"]);
    let vio = &c["vio"];
    assert_eq!(vio["status"], "initialised", "{vio}");
    let after = vio["initialised_after_s"]
        .as_f64()
        .expect("initialised_after_s");
    assert!(after < 4.0, "initialised after {after} s");
    assert!(c["world_moves"].as_u64().unwrap_or(0) >= 1, "{c}");
    // ≥ 98% of the frames posed, all in the final metric world.
    let posed = c["frames_posed"].as_u64().expect("frames_posed");
    assert!(posed as f64 >= 0.98 * 240.0, "{posed} of 240 posed");
    let ate = &c["ate"];
    let scale = ate["scale"].as_f64().expect("scale");
    assert!(
        (scale - 1.0).abs() < 0.03,
        "Sim(3) scale {scale}: not metric"
    );
    let rmse = ate["rmse_m"].as_f64().expect("rmse");
    assert!(rmse < 0.05, "ATE {rmse} m");
    // Gravity-aligned: a rigid alignment needs no scale and the tilt stays small.
    let se3 = c["ate_se3"]["rmse_percent"].as_f64().expect("ate_se3");
    assert!(se3 < 0.5, "SE(3) ATE {se3}% of the path");
    let tilt = c["ate_4dof"]["tilt_rmse_deg"].as_f64().expect("tilt");
    assert!(tilt < 1.0, "roll/pitch error {tilt}°");
    // Tracked with the IMU's prediction and prior: ≥ 90% of the frames after the
    // initialisation (20 Hz).
    let vi = c["frames_by_source"]["visual_inertial"]
        .as_u64()
        .unwrap_or(0) as f64;
    let after_init = 240.0 - after * 20.0;
    assert!(
        vi >= 0.9 * after_init,
        "{vi} visual-inertial of {after_init}"
    );
    let errors = rep["error_counts"].as_object().expect("error_counts");
    assert!(errors.keys().all(|k| !k.contains("imu")), "{errors:?}");
}

/// The same data in `mono` mode: up to scale (a Sim(3) alignment's scale far from 1), the
/// report says why it ran monocular, no inertial state.
#[test]
fn drone_mono_is_up_to_scale() {
    let tmp = tempdir();
    let ds = synthetic(tmp.path(), "drone", 120, None);
    let out = tmp.path().join("mono");
    let res = run_pipeline(
        &[&ds[0]],
        &out,
        "vio_mono",
        &["--lockstep", "--mode", "mono"],
    );
    assert!(res.status.success());
    let c = &report(&out)["clients"][0];
    assert_eq!(c["client_mode"], "mono");
    assert!(c["client_mode_reason"]
        .as_str()
        .unwrap_or("")
        .contains("mono"));
    assert!(c["vio"].is_null(), "{c}");
    let scale = c["ate"]["scale"].as_f64().expect("scale");
    assert!(
        (scale - 1.0).abs() > 0.2,
        "monocular scale {scale} came out metric"
    );
}
