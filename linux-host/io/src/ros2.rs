//! ROS 2 message types, as plain serde structs encoded with CDR (little endian).
//!
//! Each struct mirrors one ROS 2 interface field by field, in declaration order, because CDR has
//! no field names: the order *is* the format. Fixed-size arrays (`float64[36]`) are serde tuples
//! (no length prefix), unbounded arrays are `Vec`s (a `u32` count first), strings carry their
//! terminating zero, and byte arrays go through `serde_bytes` so they are copied in one piece.
//!
//! [`RosMessage`] ties a struct to its ROS type name (`sensor_msgs/msg/LaserScan`) and to the
//! `ros2msg` schema text that MCAP files carry, so that independent readers (rosbags, the
//! Python `mcap` reader, Foxglove) can decode the bags that [`crate::bag::BagWriter`] writes.

use anyhow::{Context, Result};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

/// A ROS 2 message type that can be written to and read from a bag.
pub trait RosMessage: Serialize + DeserializeOwned {
    /// The ROS 2 type name, e.g. `sensor_msgs/msg/LaserScan`.
    const TYPE_NAME: &'static str;

    /// The `ros2msg` schema: this type's definition followed by those of all nested types.
    fn schema_text() -> String {
        schema_text(Self::TYPE_NAME)
    }

    /// Encodes the message as CDR little endian, with the 4-byte encapsulation header.
    ///
    /// # Errors
    /// Only if the serializer fails, which the types of this module never make it do.
    fn to_cdr(&self) -> Result<Vec<u8>> {
        to_cdr_le(self).with_context(|| format!("encoding {} as CDR", Self::TYPE_NAME))
    }

    /// Decodes a CDR message (either byte order, with the encapsulation header).
    ///
    /// # Errors
    /// Truncated or malformed data.
    fn from_cdr(data: &[u8]) -> Result<Self> {
        let decoded = match data {
            [_, 0x00, _, _, body @ ..] => {
                cdr_encoding::from_bytes::<Self, byteorder::BigEndian>(body)
            }
            [_, 0x01, _, _, body @ ..] => {
                cdr_encoding::from_bytes::<Self, byteorder::LittleEndian>(body)
            }
            _ => anyhow::bail!(
                "decoding {}: not plain CDR (encapsulation {:02x?})",
                Self::TYPE_NAME,
                data.get(..4).unwrap_or(data)
            ),
        };
        let (message, _) =
            decoded.with_context(|| format!("decoding {} from CDR", Self::TYPE_NAME))?;
        Ok(message)
    }
}

/// `value` as plain CDR, little endian, after the encapsulation header `00 01 00 00`
/// (alignment counts from the end of the header).
fn to_cdr_le<T: Serialize>(value: &T) -> Result<Vec<u8>> {
    let mut out = vec![0x00, 0x01, 0x00, 0x00];
    cdr_encoding::to_writer::<_, byteorder::LittleEndian, _>(&mut out, value)?;
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// builtin_interfaces, std_msgs, geometry_msgs
// ---------------------------------------------------------------------------------------------

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the epoch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds within the second, `0..1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The time `ns` nanoseconds after the epoch (negative values go before it).
    /// Seconds outside the `i32` range saturate.
    pub fn from_nanos(ns: i64) -> Self {
        let sec = ns.div_euclid(1_000_000_000);
        let nanosec = ns.rem_euclid(1_000_000_000) as u32;
        let sec = sec.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32;
        Self { sec, nanosec }
    }

    /// Nanoseconds since the epoch.
    pub fn to_nanos(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    /// The time nearest to `seconds` after the epoch (an `f64` near 1e9 s resolves ~120 ns;
    /// parse decimal text with [`crate::parse_stamp_ns`] where exactness matters).
    pub fn from_secs_f64(seconds: f64) -> Self {
        Self::from_nanos((seconds * 1e9).round() as i64)
    }

    /// Seconds since the epoch as `f64`.
    pub fn as_secs_f64(self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time of the data.
    pub stamp: Time,
    /// The coordinate frame the data is expressed in.
    pub frame_id: String,
}

impl Header {
    /// A header with the given time and frame.
    pub fn new(stamp: Time, frame_id: &str) -> Self {
        Self {
            stamp,
            frame_id: frame_id.to_owned(),
        }
    }
}

/// `geometry_msgs/msg/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x (m).
    pub x: f64,
    /// y (m).
    pub y: f64,
    /// z (m).
    pub z: f64,
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x component.
    pub x: f64,
    /// y component.
    pub y: f64,
    /// z component.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion` (x, y, z, w order, as in ROS).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w (the scalar part).
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Quaternion {
    /// No rotation.
    pub const IDENTITY: Self = Self {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    };

    /// A rotation by `yaw` radians about the z axis.
    pub fn from_yaw(yaw: f64) -> Self {
        let (s, c) = (0.5 * yaw).sin_cos();
        Self {
            x: 0.0,
            y: 0.0,
            z: s,
            w: c,
        }
    }

    /// The rotation about z (yaw, radians in `(-pi, pi]`) of this quaternion; roll and pitch
    /// are ignored. Works for non-unit quaternions.
    pub fn yaw(&self) -> f64 {
        let siny = 2.0 * (self.w * self.z + self.x * self.y);
        let cosy = 1.0 - 2.0 * (self.y * self.y + self.z * self.z);
        siny.atan2(cosy)
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position (m).
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

impl Pose {
    /// A planar pose: position (x, y, 0) and a rotation `theta` about z.
    pub fn planar(x: f64, y: f64, theta: f64) -> Self {
        Self {
            position: Point { x, y, z: 0.0 },
            orientation: Quaternion::from_yaw(theta),
        }
    }

    /// The planar part `(x, y, yaw)` of this pose.
    pub fn to_planar(&self) -> (f64, f64, f64) {
        (self.position.x, self.position.y, self.orientation.yaw())
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`: a pose and its 6x6 covariance (row major, over
/// x, y, z, rotation about x, y, z).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Row-major 6x6 covariance.
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        Self {
            pose: Pose::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `geometry_msgs/msg/Twist`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity (m/s).
    pub linear: Vector3,
    /// Angular velocity (rad/s).
    pub angular: Vector3,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The velocity.
    pub twist: Twist,
    /// Row-major 6x6 covariance.
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for TwistWithCovariance {
    fn default() -> Self {
        Self {
            twist: Twist::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation (m).
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

impl Transform {
    /// A planar transform: translation (x, y, 0) and a rotation `theta` about z.
    pub fn planar(x: f64, y: f64, theta: f64) -> Self {
        Self {
            translation: Vector3 { x, y, z: 0.0 },
            rotation: Quaternion::from_yaw(theta),
        }
    }
}

/// `geometry_msgs/msg/TransformStamped`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Time and parent frame.
    pub header: Header,
    /// The frame whose pose this is.
    pub child_frame_id: String,
    /// Parent-from-child transform.
    pub transform: Transform,
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Time and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped` (e.g. `/amcl_pose`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    /// Time and frame.
    pub header: Header,
    /// The pose and its covariance.
    pub pose: PoseWithCovariance,
}

// ---------------------------------------------------------------------------------------------
// sensor_msgs, nav_msgs, tf2_msgs
// ---------------------------------------------------------------------------------------------

/// `sensor_msgs/msg/LaserScan`: a planar range scan, counter-clockwise from `angle_min`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LaserScan {
    /// Time of the first beam and the laser frame.
    pub header: Header,
    /// Angle of the first beam (rad).
    pub angle_min: f32,
    /// Angle of the last beam (rad).
    pub angle_max: f32,
    /// Angle between beams (rad).
    pub angle_increment: f32,
    /// Time between beams (s).
    pub time_increment: f32,
    /// Time between scans (s).
    pub scan_time: f32,
    /// Shortest valid range (m).
    pub range_min: f32,
    /// Longest valid range (m).
    pub range_max: f32,
    /// Ranges (m); values outside `[range_min, range_max]` are no return.
    pub ranges: Vec<f32>,
    /// Intensities, empty or one per range.
    pub intensities: Vec<f32>,
}

/// `nav_msgs/msg/Odometry`: the pose of `child_frame_id` in `header.frame_id`, and its velocity
/// in the child frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Time and the odometry frame (`odom`).
    pub header: Header,
    /// The robot frame (`base_link`).
    pub child_frame_id: String,
    /// Pose of the robot in the odometry frame.
    pub pose: PoseWithCovariance,
    /// Velocity of the robot in its own frame.
    pub twist: TwistWithCovariance,
}

/// `sensor_msgs/msg/Imu`. A covariance whose first element is -1 means "not provided".
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Imu {
    /// Time and the IMU frame.
    pub header: Header,
    /// Orientation estimate.
    pub orientation: Quaternion,
    /// Its row-major 3x3 covariance.
    pub orientation_covariance: [f64; 9],
    /// Angular rate (rad/s).
    pub angular_velocity: Vector3,
    /// Its row-major 3x3 covariance.
    pub angular_velocity_covariance: [f64; 9],
    /// Linear acceleration (m/s^2).
    pub linear_acceleration: Vector3,
    /// Its row-major 3x3 covariance.
    pub linear_acceleration_covariance: [f64; 9],
}

/// `sensor_msgs/msg/Image`: raw pixels, `step` bytes per row.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Time and the camera's optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding, e.g. `mono8`, `rgb8`, `bgr8`.
    pub encoding: String,
    /// 1 if multi-byte pixel values are big endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// `height * step` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/CompressedImage`: an encoded picture (`format` names it, e.g. `jpeg`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Time and the camera's optical frame.
    pub header: Header,
    /// `jpeg` or `png` (possibly with a prefix such as `rgb8; jpeg compressed bgr8`).
    pub format: String,
    /// The encoded file.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `tf2_msgs/msg/TFMessage`: a batch of transforms (`/tf`, `/tf_static`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `nav_msgs/msg/MapMetaData`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct MapMetaData {
    /// When the map was loaded.
    pub map_load_time: Time,
    /// Cell edge (m).
    pub resolution: f32,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Pose of cell (0, 0)'s corner in the map frame.
    pub origin: Pose,
}

/// `nav_msgs/msg/OccupancyGrid`: row-major cells from the origin, -1 unknown, 0..=100 occupied
/// probability in percent.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct OccupancyGrid {
    /// Time and the map frame.
    pub header: Header,
    /// Size, resolution and origin.
    pub info: MapMetaData,
    /// `width * height` cells, row 0 first (at the origin).
    pub data: Vec<i8>,
}

/// `nav_msgs/msg/Path`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// Time and frame.
    pub header: Header,
    /// The poses, oldest first.
    pub poses: Vec<PoseStamped>,
}

macro_rules! ros_message {
    ($($ty:ty => $name:literal),* $(,)?) => {
        $(impl RosMessage for $ty {
            const TYPE_NAME: &'static str = $name;
        })*
    };
}

ros_message! {
    LaserScan => "sensor_msgs/msg/LaserScan",
    Odometry => "nav_msgs/msg/Odometry",
    Imu => "sensor_msgs/msg/Imu",
    Image => "sensor_msgs/msg/Image",
    CompressedImage => "sensor_msgs/msg/CompressedImage",
    TfMessage => "tf2_msgs/msg/TFMessage",
    OccupancyGrid => "nav_msgs/msg/OccupancyGrid",
    PoseStamped => "geometry_msgs/msg/PoseStamped",
    PoseWithCovarianceStamped => "geometry_msgs/msg/PoseWithCovarianceStamped",
    Path => "nav_msgs/msg/Path",
}

// ---------------------------------------------------------------------------------------------
// Schemas (ros2msg)
// ---------------------------------------------------------------------------------------------

/// Field lists of every interface used here, keyed by `pkg/Name` (without `/msg/`).
const DEFINITIONS: &[(&str, &str)] = &[
    ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"),
    (
        "std_msgs/Header",
        "builtin_interfaces/Time stamp\nstring frame_id\n",
    ),
    ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"),
    (
        "geometry_msgs/Quaternion",
        "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    ),
    (
        "geometry_msgs/Pose",
        "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    ),
    (
        "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    ),
    (
        "geometry_msgs/Twist",
        "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    ),
    (
        "geometry_msgs/TwistWithCovariance",
        "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    ),
    (
        "geometry_msgs/Transform",
        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    ),
    (
        "geometry_msgs/TransformStamped",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
    ),
    (
        "geometry_msgs/PoseStamped",
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    ),
    (
        "geometry_msgs/PoseWithCovarianceStamped",
        "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n",
    ),
    (
        "sensor_msgs/LaserScan",
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n\
         float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n\
         float32[] ranges\nfloat32[] intensities\n",
    ),
    (
        "nav_msgs/Odometry",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
         geometry_msgs/TwistWithCovariance twist\n",
    ),
    (
        "sensor_msgs/Imu",
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n\
         float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n\
         float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n\
         float64[9] linear_acceleration_covariance\n",
    ),
    (
        "sensor_msgs/Image",
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n\
         uint8 is_bigendian\nuint32 step\nuint8[] data\n",
    ),
    (
        "sensor_msgs/CompressedImage",
        "std_msgs/Header header\nstring format\nuint8[] data\n",
    ),
    (
        "tf2_msgs/TFMessage",
        "geometry_msgs/TransformStamped[] transforms\n",
    ),
    (
        "nav_msgs/MapMetaData",
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\n\
         uint32 height\ngeometry_msgs/Pose origin\n",
    ),
    (
        "nav_msgs/OccupancyGrid",
        "std_msgs/Header header\nnav_msgs/MapMetaData info\nint8[] data\n",
    ),
    (
        "nav_msgs/Path",
        "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    ),
];

fn definition(short_name: &str) -> Option<&'static str> {
    DEFINITIONS
        .iter()
        .find(|(name, _)| *name == short_name)
        .map(|(_, text)| *text)
}

/// `pkg/msg/Name` or `pkg/Name` to `pkg/Name`.
fn short_name(type_name: &str) -> String {
    type_name.replacen("/msg/", "/", 1)
}

/// The nested message types a definition refers to, in order of first use.
fn nested_types(text: &str) -> impl Iterator<Item = &str> {
    text.lines().filter_map(|line| {
        let ty = line.split_whitespace().next()?;
        let ty = ty.split('[').next()?;
        ty.contains('/').then_some(ty)
    })
}

/// The `ros2msg` schema text of a type: its definition, then each nested type once, each after
/// a line of 80 `=` and a `MSG: pkg/Name` line (the layout rosbag2 writes into MCAP files).
///
/// Unknown type names give an empty text.
pub fn schema_text(type_name: &str) -> String {
    let root = short_name(type_name);
    let mut text = definition(&root).unwrap_or_default().to_owned();
    let mut done = vec![root.clone()];
    let mut queue: Vec<String> = nested_types(&text).map(str::to_owned).collect();
    let mut next = 0;
    while let Some(name) = queue.get(next).cloned() {
        next += 1;
        if done.contains(&name) {
            continue;
        }
        let Some(body) = definition(&name) else {
            continue;
        };
        text.push_str(&"=".repeat(80));
        text.push_str("\nMSG: ");
        text.push_str(&name);
        text.push('\n');
        text.push_str(body);
        queue.extend(nested_types(body).map(str::to_owned));
        done.push(name);
    }
    text
}

/// `true` for a covariance that ROS marks as "not provided" (first element -1).
pub fn covariance_unknown(cov: &[f64]) -> bool {
    cov.first().is_some_and(|&c| c == -1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_round_trips_nanoseconds() {
        for ns in [
            0_i64,
            1,
            999_999_999,
            1_000_000_000,
            976_052_890_244_111_000,
            -1,
        ] {
            assert_eq!(Time::from_nanos(ns).to_nanos(), ns);
        }
        let t = Time::from_nanos(-1);
        assert_eq!((t.sec, t.nanosec), (-1, 999_999_999));
        // f64 seconds near 1e9 resolve about 120 ns.
        let t = Time::from_secs_f64(976052890.244111).to_nanos();
        assert!((t - 976_052_890_244_111_000).abs() < 200);
    }

    #[test]
    fn quaternion_yaw_round_trips() {
        for k in -31..=31 {
            let yaw = f64::from(k) * 0.1;
            assert!((Quaternion::from_yaw(yaw).yaw() - yaw).abs() < 1e-12);
        }
    }

    #[test]
    fn header_encodes_like_ros2() {
        // Known layout: encapsulation (00 01 00 00), sec, nanosec, string length incl. NUL,
        // bytes, NUL.
        let h = Header::new(Time { sec: 1, nanosec: 2 }, "map");
        let bytes = to_cdr_le(&h).unwrap();
        assert_eq!(
            bytes,
            [0, 1, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 4, 0, 0, 0, b'm', b'a', b'p', 0]
        );
    }

    #[test]
    fn doubles_align_to_eight_after_header() {
        // Header "a" ends at offset 14 (data offsets, after the 4-byte encapsulation), so
        // the first float64 of the pose starts at 16: two padding bytes.
        let p = PoseStamped {
            header: Header::new(Time::default(), "a"),
            pose: Pose::planar(1.5, 0.0, 0.0),
        };
        let bytes = p.to_cdr().unwrap();
        assert_eq!(bytes.len(), 4 + 16 + 7 * 8);
        assert_eq!(&bytes[4 + 16..4 + 24], &1.5f64.to_le_bytes());
        assert_eq!(PoseStamped::from_cdr(&bytes).unwrap(), p);
    }

    #[test]
    fn every_message_round_trips() {
        let header = Header::new(Time::from_nanos(123_456_789_012), "laser");
        let scan = LaserScan {
            header: header.clone(),
            angle_min: -1.5,
            angle_max: 1.5,
            angle_increment: 0.01,
            time_increment: 0.0,
            scan_time: 0.1,
            range_min: 0.1,
            range_max: 30.0,
            ranges: vec![1.0, 2.0, f32::INFINITY],
            intensities: vec![],
        };
        assert_eq!(LaserScan::from_cdr(&scan.to_cdr().unwrap()).unwrap(), scan);

        let mut odom = Odometry {
            header: header.clone(),
            child_frame_id: "base_link".into(),
            ..Default::default()
        };
        odom.pose.pose = Pose::planar(1.0, 2.0, 0.3);
        odom.pose.covariance[35] = 0.5;
        odom.twist.twist.angular.z = 0.2;
        assert_eq!(Odometry::from_cdr(&odom.to_cdr().unwrap()).unwrap(), odom);

        let imu = Imu {
            header: header.clone(),
            angular_velocity: Vector3 {
                x: 0.0,
                y: 0.0,
                z: 0.7,
            },
            orientation_covariance: [-1.0, 0., 0., 0., 0., 0., 0., 0., 0.],
            ..Default::default()
        };
        let back = Imu::from_cdr(&imu.to_cdr().unwrap()).unwrap();
        assert_eq!(back, imu);
        assert!(covariance_unknown(&back.orientation_covariance));

        let image = Image {
            header: header.clone(),
            height: 2,
            width: 3,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 3,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        assert_eq!(Image::from_cdr(&image.to_cdr().unwrap()).unwrap(), image);

        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: header.clone(),
                child_frame_id: "base_laser".into(),
                transform: Transform::planar(0.1, 0.0, 0.0),
            }],
        };
        assert_eq!(TfMessage::from_cdr(&tf.to_cdr().unwrap()).unwrap(), tf);

        let grid = OccupancyGrid {
            header: header.clone(),
            info: MapMetaData {
                resolution: 0.05,
                width: 2,
                height: 1,
                ..Default::default()
            },
            data: vec![-1, 100],
        };
        assert_eq!(
            OccupancyGrid::from_cdr(&grid.to_cdr().unwrap()).unwrap(),
            grid
        );

        let path = Path {
            header: header.clone(),
            poses: vec![PoseStamped {
                header,
                pose: Pose::planar(3.0, 4.0, 1.0),
            }],
        };
        assert_eq!(Path::from_cdr(&path.to_cdr().unwrap()).unwrap(), path);
    }

    #[test]
    fn truncated_messages_are_errors() {
        let scan = LaserScan {
            ranges: vec![1.0; 10],
            ..Default::default()
        };
        let bytes = scan.to_cdr().unwrap();
        assert!(LaserScan::from_cdr(&bytes[..bytes.len() - 3]).is_err());
        assert!(LaserScan::from_cdr(&[]).is_err());
    }

    #[test]
    fn schema_lists_each_nested_type_once() {
        let text = Odometry::schema_text();
        assert!(text.starts_with("std_msgs/Header header\n"));
        for dep in [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/PoseWithCovariance",
            "geometry_msgs/Pose",
            "geometry_msgs/Point",
            "geometry_msgs/Quaternion",
            "geometry_msgs/TwistWithCovariance",
            "geometry_msgs/Twist",
            "geometry_msgs/Vector3",
        ] {
            assert_eq!(
                text.matches(&format!("\nMSG: {dep}\n")).count(),
                1,
                "{dep} in\n{text}"
            );
        }
        assert_eq!(TfMessage::schema_text().matches("MSG: ").count(), 6);
        assert!(schema_text("unknown_msgs/msg/X").is_empty());
    }

    #[test]
    fn a_string_length_beyond_the_message_is_an_error_not_an_allocation() {
        let scan = LaserScan {
            header: Header::new(Time { sec: 1, nanosec: 2 }, "laser"),
            ranges: vec![1.0; 8],
            ..Default::default()
        };
        let mut bytes = scan.to_cdr().unwrap();
        assert_eq!(LaserScan::from_cdr(&bytes).unwrap(), scan);
        // The frame id's length sits after the encapsulation, sec and nanosec.
        bytes[12..16].copy_from_slice(&0x7FFF_FFFFu32.to_le_bytes());
        assert!(LaserScan::from_cdr(&bytes).is_err());
        let big_endian = [0u8, 0x00, 0, 0, 0, 0, 0, 1];
        assert!(LaserScan::from_cdr(&big_endian).is_err());
        assert!(LaserScan::from_cdr(&[0, 7, 0, 0]).is_err());
    }
}
