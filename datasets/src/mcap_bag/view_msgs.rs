//! The ROS 2 messages a recording (`shoal run --record`) adds for viewers (Foxglove's 3D
//! panel and plots, `ros2 bag play` with RViz): the camera's transform, the server map's
//! points, a latency series. Serde types for `cdr-encoding` ([`super::msgs::encode`]) and
//! their `ros2msg` schema texts, as in [`super::msgs`].

use std::borrow::Cow;

use serde::Serialize;

use super::msgs::{
    with_deps, Bytes, Header, Quaternion, Vector3, HEADER, QUATERNION, TIME, VECTOR3,
};

/// Schema names.
pub mod names {
    /// A list of transforms (`/tf`).
    pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
    /// A point cloud.
    pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
    /// A number.
    pub const FLOAT64: &str = "std_msgs/msg/Float64";
    /// A log line (`/rosout`; Foxglove's Log panel).
    pub const LOG: &str = "rcl_interfaces/msg/Log";
    /// A pose and velocity (RViz's Odometry display).
    pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
}

/// `rcl_interfaces/msg/Log`.
#[derive(Debug, Clone, Serialize)]
pub struct Log<'a> {
    /// When.
    pub stamp: super::msgs::Time,
    /// Severity (20: `INFO`).
    pub level: u8,
    /// The logger (the service).
    pub name: Cow<'a, str>,
    /// The line.
    pub msg: Cow<'a, str>,
    /// Source file (empty).
    pub file: Cow<'a, str>,
    /// Function (empty).
    pub function: Cow<'a, str>,
    /// Source line (0).
    pub line: u32,
}

/// The `ros2msg` schema text of `rcl_interfaces/msg/Log`.
pub fn log_schema() -> String {
    with_deps(
        "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n\
         builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\nstring file\n\
         string function\nuint32 line\n",
        &[TIME],
    )
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Serialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Serialize)]
pub struct TransformStamped<'a> {
    /// Header (the parent frame).
    pub header: Header<'a>,
    /// The child frame.
    pub child_frame_id: Cow<'a, str>,
    /// The child's pose in the parent.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Serialize)]
pub struct TfMessage<'a> {
    /// The transforms.
    pub transforms: Vec<TransformStamped<'a>>,
}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, Serialize)]
pub struct PointField<'a> {
    /// Name (`x`, `y`, `z`).
    pub name: Cow<'a, str>,
    /// Byte offset in the point.
    pub offset: u32,
    /// Type (7: `FLOAT32`).
    pub datatype: u8,
    /// Elements.
    pub count: u32,
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, Serialize)]
pub struct PointCloud2<'a> {
    /// Header.
    pub header: Header<'a>,
    /// Rows (1: unordered).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The fields of a point.
    pub fields: Vec<PointField<'a>>,
    /// Multi-byte fields big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: Bytes<'a>,
    /// No invalid points.
    pub is_dense: bool,
}

impl<'a> PointCloud2<'a> {
    /// An unordered cloud of `xyz` `f32` points (`data`: 12 bytes each, little-endian) in
    /// `header.frame_id`.
    pub fn xyz(header: Header<'a>, data: &'a [u8]) -> Self {
        let field = |name: &'static str, offset| PointField {
            name: name.into(),
            offset,
            datatype: 7,
            count: 1,
        };
        let n = (data.len() / 12) as u32;
        Self {
            header,
            height: 1,
            width: n,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            is_bigendian: false,
            point_step: 12,
            row_step: 12 * n,
            data: Bytes(data),
            is_dense: true,
        }
    }
}

/// `std_msgs/msg/Float64`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Float64 {
    /// The number.
    pub data: f64,
}

/// The `ros2msg` schema text of `tf2_msgs/msg/TFMessage`.
pub fn tf_message_schema() -> String {
    with_deps(
        "geometry_msgs/TransformStamped[] transforms\n",
        &[
            (
                "geometry_msgs/TransformStamped",
                "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
            ),
            HEADER,
            TIME,
            (
                "geometry_msgs/Transform",
                "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
            ),
            VECTOR3,
            QUATERNION,
        ],
    )
}

/// The `ros2msg` schema text of `sensor_msgs/msg/PointCloud2`.
pub fn point_cloud2_schema() -> String {
    with_deps(
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n\
         bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
        &[
            HEADER,
            TIME,
            (
                "sensor_msgs/PointField",
                "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n\
                 uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\n\
                 uint8 datatype\nuint32 count\n",
            ),
        ],
    )
}

/// A 6x6 covariance (`float64[36]`, row-major; all zeros: unknown, REP 103's convention).
#[derive(Debug, Clone, Copy)]
pub struct Covariance6(pub [f64; 36]);

impl Serialize for Covariance6 {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        // A fixed-size array is laid out as a tuple (no length); serde's arrays stop at 32.
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Debug, Clone, Serialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: super::msgs::Pose,
    /// Its covariance (`[x y z rx ry rz]`).
    pub covariance: Covariance6,
}

/// `geometry_msgs/msg/Twist`.
#[derive(Debug, Clone, Serialize)]
pub struct Twist {
    /// Linear velocity.
    pub linear: Vector3,
    /// Angular velocity.
    pub angular: Vector3,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, Serialize)]
pub struct TwistWithCovariance {
    /// The velocity.
    pub twist: Twist,
    /// Its covariance.
    pub covariance: Covariance6,
}

/// `nav_msgs/msg/Odometry`: `child_frame_id`'s pose in `header.frame_id`, its velocity in
/// `child_frame_id`.
#[derive(Debug, Clone, Serialize)]
pub struct Odometry<'a> {
    /// Stamp and parent frame.
    pub header: Header<'a>,
    /// The moving frame.
    pub child_frame_id: Cow<'a, str>,
    /// Its pose.
    pub pose: PoseWithCovariance,
    /// Its velocity.
    pub twist: TwistWithCovariance,
}

/// The `ros2msg` schema text of `nav_msgs/msg/Odometry`.
pub fn odometry_schema() -> String {
    with_deps(
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
         geometry_msgs/TwistWithCovariance twist\n",
        &[
            HEADER,
            TIME,
            (
                "geometry_msgs/PoseWithCovariance",
                "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
            ),
            (
                "geometry_msgs/Pose",
                "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
            ),
            super::msgs::POINT,
            QUATERNION,
            (
                "geometry_msgs/TwistWithCovariance",
                "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
            ),
            (
                "geometry_msgs/Twist",
                "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
            ),
            VECTOR3,
        ],
    )
}

/// The `ros2msg` schema text of `std_msgs/msg/Float64`.
pub fn float64_schema() -> String {
    "float64 data\n".into()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mcap_bag::msgs::{encode, Time};

    /// A two-point cloud laid out as ROS 2 CDR: after the header, height and width, the
    /// fields (length, each name with its length and NUL, offset, datatype, count with its
    /// alignment), the flags and steps, the data.
    #[test]
    fn point_cloud_layout() {
        let data: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let header = Header {
            stamp: Time { sec: 1, nanosec: 2 },
            frame_id: "m".into(),
        };
        let bytes = encode(&PointCloud2::xyz(header, &data), 256).unwrap();
        // encapsulation, stamp, "m", height 1, width 2, 3 fields.
        let mut want = vec![0, 1, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 2, 0, 0, 0, b'm', 0];
        want.extend_from_slice(&[0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]);
        // "x": length 2, "x\0", offset 0 (aligned to 4 after 2 bytes), datatype 7, count 1.
        want.extend_from_slice(&[
            2, 0, 0, 0, b'x', 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0, 1, 0, 0, 0,
        ]);
        assert_eq!(&bytes[..want.len()], &want[..]);
        // The data closes the message, then is_dense.
        let tail = &bytes[bytes.len() - 25..];
        assert_eq!(&tail[..24], &data[..]);
        assert_eq!(tail[24], 1);
    }
}
