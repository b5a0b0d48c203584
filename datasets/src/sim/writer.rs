//! Writes simulated agents as EuRoC ASL folders (`mav0/cam0`, `mav0/imu0`,
//! `mav0/state_groundtruth_estimate0`) plus `groundtruth_cam0.txt` (TUM).

use std::fmt::Write as _;
use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};
use nalgebra::{Isometry3, Matrix3};

use super::params::SimParams;
use super::scene::Scene;
use super::world::SimWorld;
use crate::trajectory::{push_tum_line, Seconds, TumDigits, TumRow};
use crate::DatasetError;

/// What one written agent contains.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentSummary {
    /// The agent's dataset folder (holds `mav0/` and `groundtruth_cam0.txt`).
    pub dir: PathBuf,
    /// Frames written.
    pub frames: usize,
    /// IMU samples written.
    pub imu_samples: usize,
    /// Time from the first to the last frame, s.
    pub duration_s: f64,
    /// Camera path length over the frames, m.
    pub path_length_m: f64,
}

/// What [`generate`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSummary {
    /// The scenario name.
    pub scenario: String,
    /// One entry per agent.
    pub agents: Vec<AgentSummary>,
    /// Readout time t_r, ns.
    pub readout_ns: i64,
    /// Camera-IMU offset t_d, ns.
    pub time_offset_ns: i64,
    /// Frames rendered per second (rendering only, one thread).
    pub render_fps: f64,
    /// Wall time of the whole generation (scene, rendering, PNG, CSV), s.
    pub total_s: f64,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn create_dir(path: &Path) -> Result<(), DatasetError> {
    fs::create_dir_all(path).map_err(io_err(path))
}

fn write_text(path: &Path, text: &str) -> Result<(), DatasetError> {
    fs::write(path, text).map_err(io_err(path))
}

/// Generates the scenario of `params` into `out_dir`: one EuRoC ASL layout for single-agent
/// scenarios, `out_dir/agent0`, `out_dir/agent1`, ... otherwise (same world frame).
pub fn generate(params: &SimParams, out_dir: &Path) -> Result<SimSummary, DatasetError> {
    params.validate()?;
    let start = Instant::now();
    let scene = Arc::new(Scene::room(params.seed));
    let n_agents = params.scenario.n_agents();
    let mut agents = Vec::with_capacity(n_agents);
    let (mut frames, mut render_s) = (0usize, 0.0f64);
    for agent in 0..n_agents {
        let world = SimWorld::with_scene(params.clone(), agent, scene.clone())?;
        let dir = if n_agents == 1 {
            out_dir.to_path_buf()
        } else {
            out_dir.join(format!("agent{agent}"))
        };
        let (summary, secs) = write_agent(&world, &dir)?;
        frames += summary.frames;
        render_s += secs;
        agents.push(summary);
    }
    Ok(SimSummary {
        scenario: params.scenario.name().to_string(),
        agents,
        readout_ns: params.readout_ns(),
        time_offset_ns: params.time_offset_ns(),
        render_fps: if render_s > 0.0 {
            frames as f64 / render_s
        } else {
            0.0
        },
        total_s: start.elapsed().as_secs_f64(),
    })
}

/// A 4x4 `T_BS`-style YAML matrix block.
fn yaml_matrix(name: &str, t: &Isometry3<f64>) -> String {
    let m = t.to_homogeneous();
    let mut s = format!("{name}:\n  cols: 4\n  rows: 4\n  data: [");
    for r in 0..4 {
        if r > 0 {
            s.push_str("         ");
        }
        let row: Vec<String> = (0..4).map(|c| format!("{:?}", m[(r, c)])).collect();
        s.push_str(&row.join(", "));
        s.push_str(if r < 3 { ",\n" } else { "]\n" });
    }
    s
}

fn cam_yaml(world: &SimWorld) -> String {
    let c = world.camera();
    let p = world.params();
    let mut coeffs = vec![c.k1, c.k2, c.p1, c.p2];
    if c.k3 != 0.0 {
        coeffs.push(c.k3);
    }
    let coeffs: Vec<String> = coeffs.iter().map(|v| format!("{v}")).collect();
    format!(
        "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\ncomment: shoal synthetic cam0 \
         (scenario {}, agent {}, seed {})\n\n# Sensor extrinsics wrt. the body-frame.\n{}\n\
         # Camera specific definitions.\nrate_hz: {}\nresolution: [{}, {}]\ncamera_model: pinhole\n\
         intrinsics: [{}, {}, {}, {}]\ndistortion_model: radial-tangential\n\
         distortion_coefficients: [{}]\n\n# shoal extensions: rolling-shutter readout time t_r and \
         camera-IMU offset t_d (capture time = stamp + t_d).\nreadout_time_ns: {}\ntime_offset_ns: {}\n",
        p.scenario,
        world.agent(),
        p.seed,
        yaml_matrix("T_BS", &world.trajectory().t_bs),
        p.rate_hz,
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        coeffs.join(", "),
        world.readout_ns(),
        world.time_offset_ns(),
    )
}

/// A 3x3 matrix in the OpenCV YAML layout (row-major).
fn yaml_matrix3(name: &str, m: &Matrix3<f64>) -> String {
    let rows: Vec<String> = (0..3)
        .map(|r| {
            (0..3)
                .map(|c| format!("{:?}", m[(r, c)]))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .collect();
    format!(
        "{name}:\n  cols: 3\n  rows: 3\n  data: [{}]\n",
        rows.join(",\n         ")
    )
}

fn imu_yaml(world: &SimWorld) -> String {
    let p = world.params();
    let n = &p.noise;
    let k = &p.imu_intrinsics;
    let (bg, ba) = (p.initial_biases.gyro, p.initial_biases.accel);
    let truth = format!(
        "\n# shoal extensions: the true IMU errors of this dataset (seed eq. 2.53-2.56,\n\
         # a_m = T_a a_s + b_a + n_a, w_m = T_g w + T_s a_s + b_g + n_g), the biases at the\n\
         # first sample (they then walk; see state_groundtruth_estimate0), and the true\n\
         # camera-IMU offset t_d and rolling-shutter readout t_r (also in cam0/sensor.yaml).\n\
         {}{}{}initial_gyro_bias: [{:?}, {:?}, {:?}]\ninitial_accel_bias: [{:?}, {:?}, {:?}]\n\
         time_offset_ns: {}\nreadout_time_ns: {}\n",
        yaml_matrix3("T_g", &k.t_g),
        yaml_matrix3("T_s", &k.t_s),
        yaml_matrix3("T_a", &k.t_a),
        bg.x,
        bg.y,
        bg.z,
        ba.x,
        ba.y,
        ba.z,
        world.time_offset_ns(),
        world.readout_ns(),
    );
    let base = format!(
        "%YAML:1.0\n#Default imu sensor yaml file\nsensor_type: imu\ncomment: shoal synthetic imu0\n\n\
         # Sensor extrinsics wrt. the body-frame.\n{}\nrate_hz: {}\n\n\
         # inertial sensor noise model parameters (static)\ngyroscope_noise_density: {}\n\
         gyroscope_random_walk: {}\naccelerometer_noise_density: {}\naccelerometer_random_walk: {}\n",
        yaml_matrix("T_BS", &Isometry3::identity()),
        p.imu_rate_hz,
        n.gyro_noise_density,
        n.gyro_bias_rw,
        n.accel_noise_density,
        n.accel_bias_rw,
    );
    base + &truth
}

/// Writes one agent; returns its summary and the seconds spent rendering.
fn write_agent(world: &SimWorld, dir: &Path) -> Result<(AgentSummary, f64), DatasetError> {
    let mav = dir.join("mav0");
    let (cam_dir, imu_dir, gt_dir) = (
        mav.join("cam0"),
        mav.join("imu0"),
        mav.join("state_groundtruth_estimate0"),
    );
    let img_dir = cam_dir.join("data");
    for d in [&img_dir, &imu_dir, &gt_dir] {
        create_dir(d)?;
    }
    write_text(&cam_dir.join("sensor.yaml"), &cam_yaml(world))?;
    write_text(&imu_dir.join("sensor.yaml"), &imu_yaml(world))?;

    let mut imu_csv = String::from(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],\
         a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n",
    );
    for s in world.imu_samples() {
        let (g, a) = (s.gyro, s.accel);
        let _ = writeln!(
            imu_csv,
            "{},{},{},{},{},{},{}",
            s.t_ns, g[0], g[1], g[2], a[0], a[1], a[2]
        );
    }
    write_text(&imu_dir.join("data.csv"), &imu_csv)?;

    let mut gt_csv = String::from(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], \
         q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], \
         b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], \
         b_a_RS_S_z [m s^-2]\n",
    );
    for s in world.ground_truth_states() {
        let q = s.q_wb.quaternion();
        let (bg, ba) = (s.biases.gyro, s.biases.accel);
        let _ = writeln!(
            gt_csv,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            s.t_ns,
            s.p_wb.x,
            s.p_wb.y,
            s.p_wb.z,
            q.w,
            q.i,
            q.j,
            q.k,
            s.v_w.x,
            s.v_w.y,
            s.v_w.z,
            bg.x,
            bg.y,
            bg.z,
            ba.x,
            ba.y,
            ba.z
        );
    }
    write_text(&gt_dir.join("data.csv"), &gt_csv)?;

    let cam = world.camera();
    let mut buf = vec![0u8; cam.width as usize * cam.height as usize];
    let mut data_csv = String::from("#timestamp [ns],filename\n");
    let mut tum = String::from(
        "# timestamp tx ty tz qx qy qz qw (cam0 camera-to-world at the mid-row capture time)\n",
    );
    let mut render_s = 0.0;
    for k in 0..world.n_frames() {
        let t0 = Instant::now();
        world.render_frame_into(k, &mut buf)?;
        render_s += t0.elapsed().as_secs_f64();
        let stamp = world.frame_time_ns(k);
        let name = format!("{stamp}.png");
        let path = img_dir.join(&name);
        let file = File::create(&path).map_err(io_err(&path))?;
        let mut w = BufWriter::new(file);
        PngEncoder::new_with_quality(&mut w, CompressionType::Fast, FilterType::Sub)
            .write_image(&buf, cam.width, cam.height, ExtendedColorType::L8)
            .map_err(|e| DatasetError::Image {
                path: path.clone(),
                detail: e.to_string(),
            })?;
        w.flush().map_err(io_err(&path))?;
        let _ = writeln!(data_csv, "{stamp},{name}");
        let row = TumRow::from_pose(stamp, &world.pose_cam_at(world.frame_capture_time_ns(k)));
        push_tum_line(
            &mut tum,
            Seconds(row.t_ns),
            &row.t,
            &row.q,
            TumDigits::Fixed9,
        );
    }
    write_text(&cam_dir.join("data.csv"), &data_csv)?;
    write_text(&dir.join("groundtruth_cam0.txt"), &tum)?;
    let summary = AgentSummary {
        dir: dir.to_path_buf(),
        frames: world.n_frames(),
        imu_samples: world.imu_samples().len(),
        duration_s: world.duration_s(),
        path_length_m: world.path_length_m(),
    };
    Ok((summary, render_s))
}
