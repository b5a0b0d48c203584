//! The `shoal` metadata record of the MCAP files shoal writes: the stamp convention (frame
//! stamps are already middle-row times with t_d applied, so they are not converted again),
//! the topics, and the calibration the replay needs that ROS messages do not carry (T_BS,
//! t_r, t_d, rate, the IMU noise and intrinsics). Numbers are written with Rust's shortest
//! round-trip formatting, so they read back bit for bit.

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3};
use slam_core::imu::{ImuBiases, ImuIntrinsics, ImuNoise};
use slam_core::rolling_shutter::ReadoutDirection;

use crate::euroc::ImuSensorCalib;
use crate::{CameraCalib, PinholeRadtan};

/// Name of the metadata record.
pub const RECORD: &str = "shoal";
/// Its `format` value.
pub const FORMAT: &str = "shoal-mcap";
/// Its `version` value this build writes and reads.
pub const VERSION: &str = "1";
/// `time_convention` of shoal's files: stamps are middle-row times, t_d applied.
pub const MIDDLE_ROW: &str = "middle_row";

/// What the record says.
#[derive(Debug, Clone, PartialEq)]
pub struct ShoalMeta {
    /// The camera's calibration and timing.
    pub camera: CameraCalib,
    /// The IMU's calibration, when the source dataset had one.
    pub imu: Option<ImuSensorCalib>,
    /// Stamps are middle-row times (else first-row: the record is then informational).
    pub middle_row: bool,
    /// Topic of the ground-truth poses, if written.
    pub ground_truth_topic: Option<String>,
}

fn nums(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:?}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn rows(m: &Matrix3<f64>) -> String {
    nums(&std::array::from_fn::<f64, 9, _>(|i| m[(i / 3, i % 3)]))
}

/// The record's key-value map for `meta`.
pub fn to_map(meta: &ShoalMeta) -> BTreeMap<String, String> {
    let mut m = BTreeMap::new();
    let mut put = |k: &str, v: String| {
        m.insert(k.to_string(), v);
    };
    put("format", FORMAT.into());
    put("version", VERSION.into());
    let conv = if meta.middle_row {
        MIDDLE_ROW
    } else {
        "first_row"
    };
    put("time_convention", conv.into());
    let c = &meta.camera;
    let k = &c.model;
    put("camera.size", format!("{} {}", k.width, k.height));
    put("camera.pinhole", nums(&[k.fx, k.fy, k.cx, k.cy]));
    put("camera.radtan", nums(&[k.k1, k.k2, k.p1, k.p2, k.k3]));
    put("camera.readout_direction", k.readout.name().to_string());
    let (q, t) = (c.t_bs.rotation.quaternion(), c.t_bs.translation.vector);
    put("camera.t_bs_quat_xyzw", nums(&[q.i, q.j, q.k, q.w]));
    put("camera.t_bs_xyz", nums(&[t.x, t.y, t.z]));
    put("camera.t_bs_given", c.t_bs_given.to_string());
    put("camera.readout_ns", c.readout_ns.to_string());
    put("camera.time_offset_ns", c.time_offset_ns.to_string());
    put("camera.rate_hz", nums(&[c.rate_hz]));
    if let Some(topic) = &meta.ground_truth_topic {
        put("ground_truth_topic", topic.clone());
    }
    if let Some(i) = &meta.imu {
        let n = &i.noise;
        put("imu.rate_hz", nums(&[i.rate_hz]));
        put(
            "imu.noise",
            nums(&[
                n.gyro_noise_density,
                n.accel_noise_density,
                n.gyro_bias_rw,
                n.accel_bias_rw,
            ]),
        );
        if let Some(k) = &i.intrinsics {
            put("imu.t_g", rows(&k.t_g));
            put("imu.t_s", rows(&k.t_s));
            put("imu.t_a", rows(&k.t_a));
        }
        if let Some(b) = &i.initial_biases {
            put(
                "imu.initial_biases",
                nums(&[
                    b.gyro.x, b.gyro.y, b.gyro.z, b.accel.x, b.accel.y, b.accel.z,
                ]),
            );
        }
        if let Some(t) = i.time_offset_ns {
            put("imu.time_offset_ns", t.to_string());
        }
        if let Some(t) = i.readout_ns {
            put("imu.readout_ns", t.to_string());
        }
    }
    m
}

/// Reads a record written by [`to_map`]; the error names the key.
pub fn from_map(m: &BTreeMap<String, String>) -> Result<ShoalMeta, String> {
    let get = |k: &str| m.get(k).map(String::as_str).ok_or(format!("no `{k}`"));
    if get("format")? != FORMAT {
        return Err(format!("format `{}`, expected `{FORMAT}`", get("format")?));
    }
    if get("version")? != VERSION {
        return Err(format!(
            "version {} (this build reads {VERSION})",
            get("version")?
        ));
    }
    let floats = |k: &str, n: usize| -> Result<Vec<f64>, String> {
        let v: Vec<f64> = get(k)?
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| format!("`{k}`: {e}"))?;
        if v.len() != n || v.iter().any(|x| !x.is_finite()) {
            return Err(format!("`{k}` must be {n} finite numbers"));
        }
        Ok(v)
    };
    let int =
        |k: &str| -> Result<i64, String> { get(k)?.parse().map_err(|e| format!("`{k}`: {e}")) };
    let size: Vec<u32> = get("camera.size")?
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`camera.size`: {e}"))?;
    let [w, h] = size[..] else {
        return Err("`camera.size` must be width height".into());
    };
    let p = floats("camera.pinhole", 4)?;
    let d = floats("camera.radtan", 5)?;
    let mut model = PinholeRadtan::from_coefficients(
        w,
        h,
        [p[0], p[1], p[2], p[3]],
        [d[0], d[1], d[2], d[3], d[4]],
    );
    model.readout = ReadoutDirection::parse(get("camera.readout_direction")?)?;
    let q = floats("camera.t_bs_quat_xyzw", 4)?;
    let t = floats("camera.t_bs_xyz", 3)?;
    let t_bs = Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::new_unchecked(Quaternion::new(q[3], q[0], q[1], q[2])),
    );
    let camera = CameraCalib {
        model,
        t_bs,
        t_bs_given: get("camera.t_bs_given")? == "true",
        readout_ns: int("camera.readout_ns")?,
        time_offset_ns: int("camera.time_offset_ns")?,
        rate_hz: floats("camera.rate_hz", 1)?[0],
    };
    let imu = if m.contains_key("imu.noise") {
        Some(imu_from_map(m, &floats, &int)?)
    } else {
        None
    };
    Ok(ShoalMeta {
        camera,
        imu,
        middle_row: get("time_convention")? == MIDDLE_ROW,
        ground_truth_topic: m.get("ground_truth_topic").cloned(),
    })
}

type Floats<'a> = dyn Fn(&str, usize) -> Result<Vec<f64>, String> + 'a;
type Int<'a> = dyn Fn(&str) -> Result<i64, String> + 'a;

fn imu_from_map(
    m: &BTreeMap<String, String>,
    floats: &Floats,
    int: &Int,
) -> Result<ImuSensorCalib, String> {
    let n = floats("imu.noise", 4)?;
    let mat = |k: &str| floats(k, 9).map(|v| Matrix3::from_row_slice(&v));
    let intrinsics = if m.contains_key("imu.t_g") {
        Some(ImuIntrinsics {
            t_g: mat("imu.t_g")?,
            t_s: mat("imu.t_s")?,
            t_a: mat("imu.t_a")?,
        })
    } else {
        None
    };
    let initial_biases = if m.contains_key("imu.initial_biases") {
        let b = floats("imu.initial_biases", 6)?;
        Some(ImuBiases {
            gyro: Vector3::new(b[0], b[1], b[2]),
            accel: Vector3::new(b[3], b[4], b[5]),
        })
    } else {
        None
    };
    let opt_int = |k: &str| m.contains_key(k).then(|| int(k)).transpose();
    Ok(ImuSensorCalib {
        rate_hz: floats("imu.rate_hz", 1)?[0],
        noise: ImuNoise {
            gyro_noise_density: n[0],
            accel_noise_density: n[1],
            gyro_bias_rw: n[2],
            accel_bias_rw: n[3],
        },
        intrinsics,
        initial_biases,
        time_offset_ns: opt_int("imu.time_offset_ns")?,
        readout_ns: opt_int("imu.readout_ns")?,
    })
}
