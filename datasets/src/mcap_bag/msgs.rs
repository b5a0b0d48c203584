//! The ROS 2 (and Foxglove) messages a recording is read from and written with, as serde
//! types for the `cdr-encoding` crate, and their `ros2msg` schema texts.
//!
//! A ROS 2 message is CDR after a 4-byte encapsulation header (`00 01`: little-endian,
//! `00 00`: big-endian, then two option bytes); CDR alignment counts from after that header,
//! so the body is handed to `cdr-encoding` on its own.

use std::borrow::Cow;

use byteorder::{BigEndian, LittleEndian};
use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, `< 1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The time in ns; `None` when `nanosec` is not below 1e9.
    pub fn to_ns(self) -> Option<i64> {
        (self.nanosec < 1_000_000_000)
            .then(|| i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec))
    }

    /// `t_ns` as a ROS time; `None` beyond the `int32` seconds (year 2038) or before 1902.
    pub fn from_ns(t_ns: i64) -> Option<Self> {
        let sec = i32::try_from(t_ns.div_euclid(1_000_000_000)).ok()?;
        Some(Self {
            sec,
            nanosec: t_ns.rem_euclid(1_000_000_000) as u32,
        })
    }
}

/// `std_msgs/msg/Header`. (Strings are `Cow`: `cdr-encoding` hands strings over as
/// transient `&str`, so they cannot be borrowed from the message.)
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct Header<'a> {
    /// Stamp.
    pub stamp: Time,
    /// Frame name.
    #[serde(borrow)]
    pub frame_id: Cow<'a, str>,
}

/// A byte sequence (`uint8[]`) serialised in one piece (serde would write a `[u8]` byte
/// by byte).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bytes<'a>(pub &'a [u8]);

impl Serialize for Bytes<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(self.0)
    }
}

impl<'de: 'a, 'a> Deserialize<'de> for Bytes<'a> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        <&'a [u8]>::deserialize(d).map(Bytes)
    }
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Image<'a> {
    /// Header (stamp: the first row's time, by the camera-driver convention).
    #[serde(borrow)]
    pub header: Header<'a>,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`mono8`, `rgb8`, `bgr8`, ...).
    #[serde(borrow)]
    pub encoding: Cow<'a, str>,
    /// 1 for big-endian multi-byte pixels.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Pixels, `step * height` bytes.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CompressedImage<'a> {
    /// Header.
    #[serde(borrow)]
    pub header: Header<'a>,
    /// `jpeg`, `png`, or image_transport's `"<encoding>; jpeg compressed <encoding>"`.
    #[serde(borrow)]
    pub format: Cow<'a, str>,
    /// The encoded image.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}

/// `foxglove_msgs/msg/RawImage` (ROS 2 flavour).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FoxgloveRawImage<'a> {
    /// Stamp.
    pub timestamp: Time,
    /// Frame name.
    #[serde(borrow)]
    pub frame_id: Cow<'a, str>,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Pixel encoding.
    #[serde(borrow)]
    pub encoding: Cow<'a, str>,
    /// Bytes per row.
    pub step: u32,
    /// Pixels.
    #[serde(borrow)]
    pub data: Bytes<'a>,
}

/// `foxglove_msgs/msg/CompressedImage` (ROS 2 flavour).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FoxgloveCompressedImage<'a> {
    /// Stamp.
    pub timestamp: Time,
    /// Frame name.
    #[serde(borrow)]
    pub frame_id: Cow<'a, str>,
    /// The encoded image.
    #[serde(borrow)]
    pub data: Bytes<'a>,
    /// `jpeg`, `png`, ...
    #[serde(borrow)]
    pub format: Cow<'a, str>,
}

/// `geometry_msgs/msg/Vector3` (also `Point`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// `sensor_msgs/msg/Imu`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Imu<'a> {
    /// Header (stamp: the sample time).
    #[serde(borrow)]
    pub header: Header<'a>,
    /// Orientation estimate (unused; covariance[0] = -1 when there is none).
    pub orientation: Quaternion,
    /// Its covariance.
    pub orientation_covariance: [f64; 9],
    /// Angular rate, rad/s.
    pub angular_velocity: Vector3,
    /// Its covariance.
    pub angular_velocity_covariance: [f64; 9],
    /// Specific force, m/s².
    pub linear_acceleration: Vector3,
    /// Its covariance.
    pub linear_acceleration_covariance: [f64; 9],
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct RegionOfInterest {
    /// Left column.
    pub x_offset: u32,
    /// Top row.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Whether a rectified region is meant.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CameraInfo<'a> {
    /// Header.
    #[serde(borrow)]
    pub header: Header<'a>,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// `plumb_bob` (k1 k2 p1 p2 k3), `rational_polynomial`, `equidistant`, ...
    #[serde(borrow)]
    pub distortion_model: Cow<'a, str>,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsics, rows (`fx 0 cx; 0 fy cy; 0 0 1`).
    pub k: [f64; 9],
    /// Rectification rotation, rows.
    pub r: [f64; 9],
    /// Projection, rows.
    pub p: [f64; 12],
    /// Horizontal binning.
    pub binning_x: u32,
    /// Vertical binning.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Pose {
    /// Position.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoseStamped<'a> {
    /// Header.
    #[serde(borrow)]
    pub header: Header<'a>,
    /// The pose.
    pub pose: Pose,
}

/// Decodes a CDR-encapsulated ROS 2 message (either byte order); the error says what is
/// wrong, for the caller to name the file and message.
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, String> {
    let (head, body) = bytes
        .split_at_checked(4)
        .ok_or_else(|| format!("{} bytes, shorter than the CDR header", bytes.len()))?;
    let decoded = match (head[0], head[1]) {
        (0, 1) => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        (0, 0) => cdr_encoding::from_bytes::<T, BigEndian>(body),
        (a, b) => {
            return Err(format!(
                "CDR representation {a:02x} {b:02x} is not plain CDR (00 00 or 00 01)"
            ))
        }
    };
    decoded
        .map(|(value, _)| value)
        .map_err(|e| format!("CDR decoding failed: {e}"))
}

/// Encodes `value` as a little-endian CDR-encapsulated ROS 2 message.
pub fn encode<T: Serialize>(value: &T, size_hint: usize) -> Result<Vec<u8>, String> {
    let body = cdr_encoding::to_vec_with_size_hint::<T, LittleEndian>(value, size_hint)
        .map_err(|e| format!("CDR encoding failed: {e}"))?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&[0, 1, 0, 0]);
    out.extend_from_slice(&body);
    Ok(out)
}

/// The schema names this module reads.
pub mod names {
    /// ROS 2 raw image.
    pub const IMAGE: &str = "sensor_msgs/msg/Image";
    /// ROS 2 compressed image.
    pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
    /// Foxglove raw image (ROS 2 flavour).
    pub const FOXGLOVE_RAW_IMAGE: &str = "foxglove_msgs/msg/RawImage";
    /// Foxglove compressed image (ROS 2 flavour).
    pub const FOXGLOVE_COMPRESSED_IMAGE: &str = "foxglove_msgs/msg/CompressedImage";
    /// ROS 2 IMU sample.
    pub const IMU: &str = "sensor_msgs/msg/Imu";
    /// ROS 2 camera calibration.
    pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
    /// ROS 2 stamped pose (the ground truth shoal writes).
    pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";
}

const SEP: &str =
    "================================================================================\n";

/// A `ros2msg` schema text: `main`, then each dependency after a separator line.
pub(crate) fn with_deps(main: &str, deps: &[(&str, &str)]) -> String {
    let mut s = main.to_string();
    for (name, body) in deps {
        s.push_str(SEP);
        s.push_str("MSG: ");
        s.push_str(name);
        s.push('\n');
        s.push_str(body);
    }
    s
}

pub(crate) const HEADER: (&str, &str) = (
    "std_msgs/Header",
    "builtin_interfaces/Time stamp\nstring frame_id\n",
);
pub(crate) const TIME: (&str, &str) = ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n");
pub(crate) const QUATERNION: (&str, &str) = (
    "geometry_msgs/Quaternion",
    "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
);
pub(crate) const VECTOR3: (&str, &str) =
    ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n");
pub(crate) const POINT: (&str, &str) = ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n");

/// The `ros2msg` schema text of `sensor_msgs/msg/Image` (with its dependencies).
pub fn image_schema() -> String {
    with_deps(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n\
         uint8 is_bigendian\nuint32 step\nuint8[] data\n",
        &[HEADER, TIME],
    )
}

/// The `ros2msg` schema text of `sensor_msgs/msg/Imu`.
pub fn imu_schema() -> String {
    with_deps(
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n\
         float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n\
         float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n\
         float64[9] linear_acceleration_covariance\n",
        &[HEADER, TIME, QUATERNION, VECTOR3],
    )
}

/// The `ros2msg` schema text of `sensor_msgs/msg/CameraInfo`.
pub fn camera_info_schema() -> String {
    with_deps(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n\
         float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n\
         uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
        &[
            HEADER,
            TIME,
            (
                "sensor_msgs/RegionOfInterest",
                "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
            ),
        ],
    )
}

/// The `ros2msg` schema text of `geometry_msgs/msg/PoseStamped`.
pub fn pose_stamped_schema() -> String {
    with_deps(
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
        &[
            HEADER,
            TIME,
            (
                "geometry_msgs/Pose",
                "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
            ),
            POINT,
            QUATERNION,
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ROS 2 `Image` laid out by hand (fastcdr's layout: 4-byte length before each string
    /// with its NUL, u8 fields unaligned, u32 aligned to 4 from the end of the header).
    #[test]
    fn image_layout_is_ros2_cdr() {
        let img = Image {
            header: Header {
                stamp: Time { sec: 7, nanosec: 9 },
                frame_id: "cam".into(),
            },
            height: 1,
            width: 2,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 2,
            data: Bytes(&[10, 20]),
        };
        let bytes = encode(&img, 64).unwrap();
        let mut want = vec![0, 1, 0, 0, 7, 0, 0, 0, 9, 0, 0, 0, 4, 0, 0, 0];
        want.extend_from_slice(b"cam\0");
        want.extend_from_slice(&[1, 0, 0, 0, 2, 0, 0, 0, 6, 0, 0, 0]);
        want.extend_from_slice(b"mono8\0");
        want.extend_from_slice(&[0, 0]); // is_bigendian at 34, one byte of padding to 36
        want.extend_from_slice(&[2, 0, 0, 0, 2, 0, 0, 0, 10, 20]);
        assert_eq!(bytes, want);
        let back: Image = decode(&bytes).unwrap();
        assert_eq!(
            (back.width, &*back.encoding, back.data.0),
            (2, "mono8", &[10u8, 20][..])
        );
        assert_eq!(back.header.stamp.to_ns(), Some(7_000_000_009));
    }

    #[test]
    fn big_endian_and_bad_headers() {
        // Time 1 s 2 ns big-endian, frame "" (length 1: the NUL).
        let be = [0u8, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 1, 0];
        let h: Header = decode(&be).unwrap();
        assert_eq!(h.stamp.to_ns(), Some(1_000_000_002));
        assert!(decode::<Header>(&[0, 1]).unwrap_err().contains("shorter"));
        assert!(decode::<Header>(&[0, 7, 0, 0, 1])
            .unwrap_err()
            .contains("not plain CDR"));
        assert!(decode::<Header>(&[0, 1, 0, 0, 1, 2])
            .unwrap_err()
            .contains("CDR decoding failed"));
    }

    #[test]
    fn time_conversions() {
        assert_eq!(
            Time::from_ns(-1).unwrap(),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
        assert_eq!(Time::from_ns(-1).unwrap().to_ns(), Some(-1));
        assert!(Time::from_ns(i64::MAX).is_none());
        assert!(Time {
            sec: 0,
            nanosec: 1_000_000_000
        }
        .to_ns()
        .is_none());
    }
}
