//! ROS 2 message types, written once: the DDS node publishes them and the recorder writes them
//! into bags, from the same structs and the same definitions.
//!
//! Every type is a serde struct whose fields are in the order of its `.msg` definition, which is
//! the order of the CDR encoding (OMG CDR as ROS 2's rmw layers use it: XCDR1, little endian,
//! primitives aligned to their size counted from the start of the payload after the 4-byte
//! encapsulation header; strings are a `u32` length including the NUL terminator, then the
//! bytes and the NUL; sequences a `u32` element count then the elements; fixed arrays just the
//! elements). Each type carries a [`MsgDef`]: its ROS name (`geometry_msgs/msg/Twist`), its
//! `.msg` text and the definitions it uses, from which
//!
//! - [`MsgDef::dds_type_name`] gives the DDS type name (`geometry_msgs::msg::dds_::Twist_`);
//! - [`MsgDef::full_definition`] gives the schema text rosbag2 writes into MCAP `ros2msg`
//!   schemas: the type's own text, then each dependency once, depth first, each after a line
//!   of 80 `=` and a line `MSG: pkg/Type`.
//!
//! The `.msg` texts here list the fields (and constants) of the upstream definitions in their
//! order, with fully qualified type names and without the upstream comments; field names,
//! types and order are what a decoder needs and they match the upstream packages
//! (builtin_interfaces, std_msgs, geometry_msgs, nav_msgs, tf2_msgs, sensor_msgs,
//! diagnostic_msgs and std_srvs of ROS 2, and can_msgs of ros-industrial/ros_canopen).
//!
//! `rollbase_msgs/msg/*` are rollbase's own per-cycle records (see [`crate::record`]); no ROS
//! installation has them, so `ros2 bag play` skips their topics, while readers that decode
//! from the schema text in the file (rosbags, Foxglove, mcap-ros2-support) read them.

use serde::de::{DeserializeOwned, SeqAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::collections::BTreeSet;

/// A message definition: ROS name, `.msg` text, and the definitions its fields use.
#[derive(Debug)]
pub struct MsgDef {
    /// Full ROS name, `package/msg/Type` (`package/srv/Type_Request` for service parts).
    pub name: &'static str,
    /// The `.msg` text (fields and constants, one per line).
    pub text: &'static str,
    /// Definitions of the non-primitive field types (direct dependencies).
    pub deps: &'static [&'static MsgDef],
}

impl MsgDef {
    /// The DDS type name rmw implementations use: `pkg::msg::dds_::Type_`.
    pub fn dds_type_name(&self) -> String {
        let mut parts = self.name.split('/');
        let (pkg, kind, ty) = (
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
        );
        format!("{pkg}::{kind}::dds_::{ty}_")
    }

    /// The name rosbag2 writes in MCAP schema records and in `MSG:` lines: `pkg/Type` for the
    /// dependency lines, `pkg/msg/Type` for the schema name.
    fn short_name(&self) -> String {
        let mut parts = self.name.split('/');
        let pkg = parts.next().unwrap_or_default();
        let ty = parts.nth(1).unwrap_or_default();
        format!("{pkg}/{ty}")
    }

    /// The schema text rosbag2 stores for this type: own text, then every dependency once
    /// (depth first) after a separator line of 80 `=` and `MSG: pkg/Type`.
    pub fn full_definition(&self) -> String {
        let mut out = String::from(self.text.trim_end());
        out.push('\n');
        let mut seen = BTreeSet::new();
        seen.insert(self.name);
        self.append_deps(&mut out, &mut seen);
        out
    }

    fn append_deps(&self, out: &mut String, seen: &mut BTreeSet<&'static str>) {
        for d in self.deps {
            if seen.insert(d.name) {
                out.push_str(&"=".repeat(80));
                out.push('\n');
                out.push_str("MSG: ");
                out.push_str(&d.short_name());
                out.push('\n');
                out.push_str(d.text.trim_end());
                out.push('\n');
                d.append_deps(out, seen);
            }
        }
    }
}

/// A ROS 2 message type: serde in `.msg` field order plus its definition.
pub trait RosMsg: Serialize + DeserializeOwned {
    /// The definition.
    const DEF: &'static MsgDef;
}

/// Errors of the CDR codec.
#[derive(Debug, thiserror::Error)]
pub enum MsgError {
    /// Encoding failed (only for values the format cannot hold, e.g. a sequence longer than
    /// 2³² elements).
    #[error("CDR encoding of {ty} failed: {message}")]
    Encode {
        /// Message type.
        ty: &'static str,
        /// What the codec reported.
        message: String,
    },
    /// The bytes are not a CDR message of this type.
    #[error("{ty}: not a valid CDR message ({len} bytes): {message}")]
    Decode {
        /// Message type.
        ty: &'static str,
        /// Length of the data.
        len: usize,
        /// What is wrong.
        message: String,
    },
}

/// CDR encapsulation header for little-endian plain CDR (`CDR_LE`): representation id 0x0001,
/// options 0.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Encodes a message as a serialized ROS 2 message: the 4-byte encapsulation header
/// ([`CDR_LE_HEADER`]) and the little-endian CDR payload. This is the byte string rosbag2
/// stores in MCAP `cdr` messages and the DDS sample payload.
pub fn to_cdr<T: RosMsg>(msg: &T) -> Result<Vec<u8>, MsgError> {
    let mut out = Vec::with_capacity(64);
    out.extend_from_slice(&CDR_LE_HEADER);
    cdr_encoding::to_writer::<T, byteorder::LittleEndian, _>(&mut out, msg).map_err(|e| {
        MsgError::Encode {
            ty: T::DEF.name,
            message: e.to_string(),
        }
    })?;
    Ok(out)
}

/// Decodes a serialized ROS 2 message (encapsulation header + CDR payload, little or big
/// endian). Trailing padding after the last field is accepted.
pub fn from_cdr<T: RosMsg>(bytes: &[u8]) -> Result<T, MsgError> {
    let err = |message: String| MsgError::Decode {
        ty: T::DEF.name,
        len: bytes.len(),
        message,
    };
    if bytes.len() < 4 {
        return Err(err("shorter than the 4-byte encapsulation header".into()));
    }
    let payload = &bytes[4..];
    let r = match (bytes[0], bytes[1]) {
        (0x00, 0x01) => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(payload),
        (0x00, 0x00) => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(payload),
        (a, b) => {
            return Err(err(format!(
                "encapsulation {a:#04x}{b:02x} is not plain CDR (0x0000 big endian, 0x0001 little endian)"
            )))
        }
    };
    r.map(|(v, _)| v).map_err(|e| err(e.to_string()))
}

/// Decodes a CDR payload (without the encapsulation header) of `T`; returns the value and the
/// number of bytes it took (the caller decides what trailing bytes mean).
pub fn from_cdr_payload<T: RosMsg>(
    payload: &[u8],
    big_endian: bool,
) -> Result<(T, usize), MsgError> {
    let r = if big_endian {
        cdr_encoding::from_bytes::<T, byteorder::BigEndian>(payload)
    } else {
        cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(payload)
    };
    r.map_err(|e| MsgError::Decode {
        ty: T::DEF.name,
        len: payload.len(),
        message: e.to_string(),
    })
}

/// serde for `float64[36]` (serde derives arrays up to 32 elements): a fixed-size tuple, as
/// CDR encodes fixed arrays (no length).
pub mod array36 {
    use super::*;

    /// Serializes the 36 elements as a tuple.
    pub fn serialize<S: Serializer>(a: &[f64; 36], s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for x in a {
            t.serialize_element(x)?;
        }
        t.end()
    }

    struct V;
    impl<'de> Visitor<'de> for V {
        type Value = [f64; 36];
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("36 float64")
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
            let mut a = [0.0; 36];
            for (i, x) in a.iter_mut().enumerate() {
                *x = seq
                    .next_element()?
                    .ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
            }
            Ok(a)
        }
    }

    /// Deserializes 36 elements from a tuple.
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<[f64; 36], D::Error> {
        d.deserialize_tuple(36, V)
    }
}

macro_rules! def {
    ($ident:ident, $name:literal, $text:literal, [$($dep:expr),* $(,)?]) => {
        #[doc = concat!("Definition of `", $name, "`.")]
        pub static $ident: MsgDef = MsgDef { name: $name, text: $text, deps: &[$(&$dep),*] };
    };
}

macro_rules! rosmsg {
    ($ty:ty, $def:ident) => {
        impl RosMsg for $ty {
            const DEF: &'static MsgDef = &$def;
        }
    };
}

// ---------------------------------------------------------------------------------------------
// Definitions
// ---------------------------------------------------------------------------------------------

def!(
    TIME,
    "builtin_interfaces/msg/Time",
    "int32 sec\nuint32 nanosec\n",
    []
);
def!(
    HEADER,
    "std_msgs/msg/Header",
    "builtin_interfaces/Time stamp\nstring frame_id\n",
    [TIME]
);
def!(
    VECTOR3,
    "geometry_msgs/msg/Vector3",
    "float64 x\nfloat64 y\nfloat64 z\n",
    []
);
def!(
    POINT,
    "geometry_msgs/msg/Point",
    "float64 x\nfloat64 y\nfloat64 z\n",
    []
);
def!(
    QUATERNION,
    "geometry_msgs/msg/Quaternion",
    "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    []
);
def!(
    POSE,
    "geometry_msgs/msg/Pose",
    "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    [POINT, QUATERNION]
);
def!(
    POSE_WITH_COVARIANCE,
    "geometry_msgs/msg/PoseWithCovariance",
    "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    [POSE]
);
def!(
    TWIST,
    "geometry_msgs/msg/Twist",
    "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    [VECTOR3]
);
def!(
    TWIST_STAMPED,
    "geometry_msgs/msg/TwistStamped",
    "std_msgs/Header header\ngeometry_msgs/Twist twist\n",
    [HEADER, TWIST]
);
def!(
    TWIST_WITH_COVARIANCE,
    "geometry_msgs/msg/TwistWithCovariance",
    "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    [TWIST]
);
def!(
    TRANSFORM,
    "geometry_msgs/msg/Transform",
    "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    [VECTOR3, QUATERNION]
);
def!(
    TRANSFORM_STAMPED,
    "geometry_msgs/msg/TransformStamped",
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
    [HEADER, TRANSFORM]
);
def!(
    ODOMETRY,
    "nav_msgs/msg/Odometry",
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
    [HEADER, POSE_WITH_COVARIANCE, TWIST_WITH_COVARIANCE]
);
def!(
    TF_MESSAGE,
    "tf2_msgs/msg/TFMessage",
    "geometry_msgs/TransformStamped[] transforms\n",
    [TRANSFORM_STAMPED]
);
def!(
    JOINT_STATE,
    "sensor_msgs/msg/JointState",
    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
    [HEADER]
);
def!(
    KEY_VALUE,
    "diagnostic_msgs/msg/KeyValue",
    "string key\nstring value\n",
    []
);
def!(
    DIAGNOSTIC_STATUS,
    "diagnostic_msgs/msg/DiagnosticStatus",
    "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n",
    [KEY_VALUE]
);
def!(
    DIAGNOSTIC_ARRAY,
    "diagnostic_msgs/msg/DiagnosticArray",
    "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
    [HEADER, DIAGNOSTIC_STATUS]
);
def!(STRING, "std_msgs/msg/String", "string data\n", []);
def!(
    MULTI_ARRAY_DIMENSION,
    "std_msgs/msg/MultiArrayDimension",
    "string label\nuint32 size\nuint32 stride\n",
    []
);
def!(
    MULTI_ARRAY_LAYOUT,
    "std_msgs/msg/MultiArrayLayout",
    "std_msgs/MultiArrayDimension[] dim\nuint32 data_offset\n",
    [MULTI_ARRAY_DIMENSION]
);
def!(
    FLOAT64_MULTI_ARRAY,
    "std_msgs/msg/Float64MultiArray",
    "std_msgs/MultiArrayLayout layout\nfloat64[] data\n",
    [MULTI_ARRAY_LAYOUT]
);
def!(
    TRIGGER_REQUEST,
    "std_srvs/srv/Trigger_Request",
    "uint8 structure_needs_at_least_one_member\n",
    []
);
def!(
    TRIGGER_RESPONSE,
    "std_srvs/srv/Trigger_Response",
    "bool success\nstring message\n",
    []
);
def!(
    CAN_FRAME,
    "can_msgs/msg/Frame",
    "std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\nbool is_error\nuint8 dlc\nuint8[8] data\n",
    [HEADER]
);

// rollbase's own records.
def!(
    RB_FRAME_REJECTION,
    "rollbase_msgs/msg/FrameRejection",
    "std_msgs/Header header\nuint32 id\nuint8 dlc\nuint8[8] data\nstring error\n",
    [HEADER]
);
def!(
    RB_WHEEL_FEEDBACK,
    "rollbase_msgs/msg/WheelFeedback",
    "uint8 node\nfloat64 steer_angle\nfloat64 steer_rate\nfloat64 wheel_speed\nfloat64 leg\nfloat64 leg_rate\nuint32 age_cycles\nuint8 module_state\n",
    []
);
def!(
    RB_FEEDBACK,
    "rollbase_msgs/msg/Feedback",
    "std_msgs/Header header\nuint64 cycle\nrollbase_msgs/WheelFeedback[] wheels\n",
    [HEADER, RB_WHEEL_FEEDBACK]
);
def!(
    RB_REFERENCE,
    "rollbase_msgs/msg/Reference",
    "std_msgs/Header header\nuint64 cycle\nfloat64 t\nfloat64[] z\nfloat64[] dz\nfloat64[] ddz\nfloat64[] nominal_z\nfloat64[] nominal_dz\n",
    [HEADER]
);
def!(
    RB_COMMAND,
    "rollbase_msgs/msg/Command",
    "std_msgs/Header header\nuint64 cycle\nstring mode\nbool enable\nfloat64[] wheel_speed\nfloat64[] steer_rate\n",
    [HEADER]
);
def!(
    RB_POSE,
    "rollbase_msgs/msg/Pose",
    "std_msgs/Header header\nuint64 cycle\nfloat64 x\nfloat64 y\nfloat64 theta\nfloat64 vx\nfloat64 vy\nfloat64 omega\nfloat64 slip_residual\nbool has_truth\nfloat64 true_x\nfloat64 true_y\nfloat64 true_theta\nfloat64[] true_legs\n",
    [HEADER]
);
def!(
    RB_ICR,
    "rollbase_msgs/msg/Icr",
    "std_msgs/Header header\nuint64 cycle\nbool at_infinity\nfloat64 icr_x\nfloat64 icr_y\nbool active\nfloat64 min_distance\nint32 nearest_wheel\nfloat64[] d_start\nfloat64[] deviation\nfloat64[] wheel_x\nfloat64[] wheel_y\n",
    [HEADER]
);
def!(
    RB_SUPERVISOR,
    "rollbase_msgs/msg/Supervisor",
    "std_msgs/Header header\nuint64 cycle\nstring state\nstring reason\n",
    [HEADER]
);
def!(
    RB_TIMING,
    "rollbase_msgs/msg/Timing",
    "std_msgs/Header header\nuint64 cycle\nfloat64 period_us\nfloat64 wakeup_latency_us\nfloat64 compute_us\nfloat64 feedback_age_us\nuint32 frames_in\nuint32 frames_out\nuint32 rejected\nbool deadline_miss\n",
    [HEADER]
);

/// Every definition of this module (for tools and tests that check them against upstream).
pub static ALL: [&MsgDef; 34] = [
    &TIME,
    &HEADER,
    &VECTOR3,
    &POINT,
    &QUATERNION,
    &POSE,
    &POSE_WITH_COVARIANCE,
    &TWIST,
    &TWIST_STAMPED,
    &TWIST_WITH_COVARIANCE,
    &TRANSFORM,
    &TRANSFORM_STAMPED,
    &ODOMETRY,
    &TF_MESSAGE,
    &JOINT_STATE,
    &KEY_VALUE,
    &DIAGNOSTIC_STATUS,
    &DIAGNOSTIC_ARRAY,
    &STRING,
    &MULTI_ARRAY_DIMENSION,
    &MULTI_ARRAY_LAYOUT,
    &FLOAT64_MULTI_ARRAY,
    &TRIGGER_REQUEST,
    &TRIGGER_RESPONSE,
    &CAN_FRAME,
    &RB_FRAME_REJECTION,
    &RB_WHEEL_FEEDBACK,
    &RB_FEEDBACK,
    &RB_REFERENCE,
    &RB_COMMAND,
    &RB_POSE,
    &RB_ICR,
    &RB_SUPERVISOR,
    &RB_TIMING,
];

// ---------------------------------------------------------------------------------------------
// Types
// ---------------------------------------------------------------------------------------------

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds within the second (0..1e9).
    pub nanosec: u32,
}

impl Time {
    /// A time from nanoseconds since the epoch (saturates at the 2038 limit of `int32 sec`).
    pub fn from_ns(ns: u64) -> Self {
        let sec = (ns / 1_000_000_000).min(i32::MAX as u64) as i32;
        Self {
            sec,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the epoch (negative times give 0).
    pub fn to_ns(self) -> u64 {
        (self.sec.max(0) as u64) * 1_000_000_000 + u64::from(self.nanosec)
    }
}

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Time stamp.
    pub stamp: Time,
    /// Coordinate frame.
    pub frame_id: String,
}

impl Header {
    /// A header at `ns` nanoseconds in frame `frame_id`.
    pub fn new(ns: u64, frame_id: &str) -> Self {
        Self {
            stamp: Time::from_ns(ns),
            frame_id: frame_id.to_string(),
        }
    }
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
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

impl Default for Quaternion {
    fn default() -> Self {
        Self::from_yaw(0.0)
    }
}

impl Quaternion {
    /// The rotation by `yaw` about z.
    pub fn from_yaw(yaw: f64) -> Self {
        let (s, c) = (0.5 * yaw).sin_cos();
        Self {
            x: 0.0,
            y: 0.0,
            z: s,
            w: c,
        }
    }

    /// The yaw of a rotation about z (`atan2(2(wz + xy), 1 − 2(y² + z²))`).
    pub fn yaw(&self) -> f64 {
        (2.0 * (self.w * self.z + self.x * self.y))
            .atan2(1.0 - 2.0 * (self.y * self.y + self.z * self.z))
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// Pose.
    pub pose: Pose,
    /// Row-major 6×6 covariance of (x, y, z, rot x, rot y, rot z).
    #[serde(with = "array36")]
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
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity (m/s).
    pub linear: Vector3,
    /// Angular velocity (rad/s).
    pub angular: Vector3,
}

/// `geometry_msgs/msg/TwistStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistStamped {
    /// Header.
    pub header: Header,
    /// Twist.
    pub twist: Twist,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// Twist.
    pub twist: Twist,
    /// Row-major 6×6 covariance of (vx, vy, vz, ωx, ωy, ωz).
    #[serde(with = "array36")]
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
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Header (frame_id: the parent frame).
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// Transform parent → child.
    pub transform: Transform,
}

/// `nav_msgs/msg/Odometry`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Header (frame_id: the odometry frame).
    pub header: Header,
    /// The base frame (frame of the twist).
    pub child_frame_id: String,
    /// Pose in the odometry frame.
    pub pose: PoseWithCovariance,
    /// Twist in the child frame.
    pub twist: TwistWithCovariance,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TFMessage {
    /// Transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `sensor_msgs/msg/JointState`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    /// Header.
    pub header: Header,
    /// Joint names.
    pub name: Vec<String>,
    /// Positions (rad or m).
    pub position: Vec<f64>,
    /// Velocities (rad/s or m/s).
    pub velocity: Vec<f64>,
    /// Efforts (empty: not measured).
    pub effort: Vec<f64>,
}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyValue {
    /// Key.
    pub key: String,
    /// Value.
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// Level: [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE`.
    pub level: u8,
    /// Name of the component.
    pub name: String,
    /// Summary.
    pub message: String,
    /// Hardware identifier.
    pub hardware_id: String,
    /// Values.
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    /// Level OK.
    pub const OK: u8 = 0;
    /// Level WARN.
    pub const WARN: u8 = 1;
    /// Level ERROR.
    pub const ERROR: u8 = 2;
    /// Level STALE.
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// Header.
    pub header: Header,
    /// One status per component.
    pub status: Vec<DiagnosticStatus>,
}

/// `std_msgs/msg/String`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}

/// `std_msgs/msg/MultiArrayDimension`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MultiArrayDimension {
    /// Label.
    pub label: String,
    /// Size.
    pub size: u32,
    /// Stride.
    pub stride: u32,
}

/// `std_msgs/msg/MultiArrayLayout`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MultiArrayLayout {
    /// Dimensions.
    pub dim: Vec<MultiArrayDimension>,
    /// Offset of the first element.
    pub data_offset: u32,
}

/// `std_msgs/msg/Float64MultiArray`: the leg command topic's type (one target extension per
/// wheel, m, in controller order; the layout is not used).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Float64MultiArray {
    /// Layout (ignored on receive; written with one dimension "legs").
    pub layout: MultiArrayLayout,
    /// Data.
    pub data: Vec<f64>,
}

/// `std_srvs/srv/Trigger` request (empty; IDL structs need a member, hence the placeholder
/// byte every ROS 2 type generator adds).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerRequest {
    /// Placeholder, 0.
    pub structure_needs_at_least_one_member: u8,
}

/// `std_srvs/srv/Trigger` response.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerResponse {
    /// Whether the request was carried out.
    pub success: bool,
    /// What happened.
    pub message: String,
}

/// `can_msgs/msg/Frame` (ros-industrial/ros_canopen, used by ros2_socketcan).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CanFrame {
    /// Header (stamp: the frame's time; frame_id: the CAN interface).
    pub header: Header,
    /// Identifier.
    pub id: u32,
    /// Remote transmission request.
    pub is_rtr: bool,
    /// 29-bit identifier.
    pub is_extended: bool,
    /// Error frame.
    pub is_error: bool,
    /// Data length.
    pub dlc: u8,
    /// Payload (first `dlc` bytes valid).
    pub data: [u8; 8],
}

/// `rollbase_msgs/msg/FrameRejection`: a received frame the receive path refused.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameRejection {
    /// Header (stamp: receive time).
    pub header: Header,
    /// Identifier.
    pub id: u32,
    /// Data length.
    pub dlc: u8,
    /// Payload.
    pub data: [u8; 8],
    /// Rejection kind (CRC, counter, DLC, range …).
    pub error: String,
}

/// `rollbase_msgs/msg/WheelFeedback`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WheelFeedback {
    /// CAN node.
    pub node: u8,
    /// Steering angle (rad).
    pub steer_angle: f64,
    /// Steering rate (rad/s).
    pub steer_rate: f64,
    /// Wheel spin rate (rad/s).
    pub wheel_speed: f64,
    /// Leg extension (m).
    pub leg: f64,
    /// Leg rate (m/s).
    pub leg_rate: f64,
    /// Cycles since the last valid feedback.
    pub age_cycles: u32,
    /// Module state (wire value; 255 unknown).
    pub module_state: u8,
}

/// `rollbase_msgs/msg/Feedback`: decoded feedback of one cycle.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Feedback {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// Per wheel.
    pub wheels: Vec<WheelFeedback>,
}

/// `rollbase_msgs/msg/Reference`: nominal and tracked reference of one cycle (z = (x, y, θ,
/// λ_1 … λ_n)).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Reference {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// Reference time (s).
    pub t: f64,
    /// Tracked z*.
    pub z: Vec<f64>,
    /// Tracked ż*.
    pub dz: Vec<f64>,
    /// Tracked z̈*.
    pub ddz: Vec<f64>,
    /// Nominal z*.
    pub nominal_z: Vec<f64>,
    /// Nominal ż*.
    pub nominal_dz: Vec<f64>,
}

/// `rollbase_msgs/msg/Command`: what the cycle sent.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CycleCommand {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// Supervisor mode name.
    pub mode: String,
    /// Enable flag.
    pub enable: bool,
    /// Wheel spin rates (rad/s).
    pub wheel_speed: Vec<f64>,
    /// Steering rates (rad/s).
    pub steer_rate: Vec<f64>,
}

/// `rollbase_msgs/msg/Pose`: estimated (and, when simulated, true) pose of one cycle.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CyclePose {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// Estimated x (m).
    pub x: f64,
    /// Estimated y (m).
    pub y: f64,
    /// Estimated θ (rad).
    pub theta: f64,
    /// Body vx (m/s).
    pub vx: f64,
    /// Body vy (m/s).
    pub vy: f64,
    /// Body ω (rad/s).
    pub omega: f64,
    /// Odometry slip residual (m/s).
    pub slip_residual: f64,
    /// Whether the true fields hold a simulated truth (else NaN).
    pub has_truth: bool,
    /// True x (m).
    pub true_x: f64,
    /// True y (m).
    pub true_y: f64,
    /// True θ (rad).
    pub true_theta: f64,
    /// True legs (m); empty without truth.
    pub true_legs: Vec<f64>,
}

/// `rollbase_msgs/msg/Icr`: the ICR and the avoidance of one cycle.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Icr {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// ICR at infinity (pure translation) or undefined: `icr_x`, `icr_y` are NaN.
    pub at_infinity: bool,
    /// ICR x in the body frame (m).
    pub icr_x: f64,
    /// ICR y in the body frame (m).
    pub icr_y: f64,
    /// Avoidance pushing.
    pub active: bool,
    /// Smallest ICR–wheel distance (m; inf at infinity).
    pub min_distance: f64,
    /// Wheel nearest the ICR, −1 when none.
    pub nearest_wheel: i32,
    /// Field radii per wheel (m).
    pub d_start: Vec<f64>,
    /// Deviation from the nominal reference.
    pub deviation: Vec<f64>,
    /// Wheel contact points x, body frame (m).
    pub wheel_x: Vec<f64>,
    /// Wheel contact points y, body frame (m).
    pub wheel_y: Vec<f64>,
}

/// `rollbase_msgs/msg/Supervisor`: state and fault reason of one cycle.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Supervisor {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// State name.
    pub state: String,
    /// Fault reason, empty when none.
    pub reason: String,
}

/// `rollbase_msgs/msg/Timing`: timing of one cycle.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// Header.
    pub header: Header,
    /// Cycle index.
    pub cycle: u64,
    /// Period (µs).
    pub period_us: f64,
    /// Wake-up latency (µs).
    pub wakeup_latency_us: f64,
    /// Compute time (µs).
    pub compute_us: f64,
    /// Feedback age (µs).
    pub feedback_age_us: f64,
    /// Frames received.
    pub frames_in: u32,
    /// Frames sent.
    pub frames_out: u32,
    /// Frames rejected.
    pub rejected: u32,
    /// Deadline missed.
    pub deadline_miss: bool,
}

rosmsg!(Time, TIME);
rosmsg!(Header, HEADER);
rosmsg!(Vector3, VECTOR3);
rosmsg!(Point, POINT);
rosmsg!(Quaternion, QUATERNION);
rosmsg!(Pose, POSE);
rosmsg!(PoseWithCovariance, POSE_WITH_COVARIANCE);
rosmsg!(Twist, TWIST);
rosmsg!(TwistStamped, TWIST_STAMPED);
rosmsg!(TwistWithCovariance, TWIST_WITH_COVARIANCE);
rosmsg!(Transform, TRANSFORM);
rosmsg!(TransformStamped, TRANSFORM_STAMPED);
rosmsg!(Odometry, ODOMETRY);
rosmsg!(TFMessage, TF_MESSAGE);
rosmsg!(JointState, JOINT_STATE);
rosmsg!(KeyValue, KEY_VALUE);
rosmsg!(DiagnosticStatus, DIAGNOSTIC_STATUS);
rosmsg!(DiagnosticArray, DIAGNOSTIC_ARRAY);
rosmsg!(StringMsg, STRING);
rosmsg!(MultiArrayDimension, MULTI_ARRAY_DIMENSION);
rosmsg!(MultiArrayLayout, MULTI_ARRAY_LAYOUT);
rosmsg!(Float64MultiArray, FLOAT64_MULTI_ARRAY);
rosmsg!(TriggerRequest, TRIGGER_REQUEST);
rosmsg!(TriggerResponse, TRIGGER_RESPONSE);
rosmsg!(CanFrame, CAN_FRAME);
rosmsg!(FrameRejection, RB_FRAME_REJECTION);
rosmsg!(WheelFeedback, RB_WHEEL_FEEDBACK);
rosmsg!(Feedback, RB_FEEDBACK);
rosmsg!(Reference, RB_REFERENCE);
rosmsg!(CycleCommand, RB_COMMAND);
rosmsg!(CyclePose, RB_POSE);
rosmsg!(Icr, RB_ICR);
rosmsg!(Supervisor, RB_SUPERVISOR);
rosmsg!(Timing, RB_TIMING);

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip<T: RosMsg + PartialEq + std::fmt::Debug>(v: &T) {
        let bytes = to_cdr(v).unwrap();
        assert_eq!(&bytes[..4], &CDR_LE_HEADER);
        let back: T = from_cdr(&bytes).unwrap();
        assert_eq!(&back, v, "{}", T::DEF.name);
    }

    #[test]
    fn twist_golden_bytes() {
        // Header 00 01 00 00 (CDR_LE), then six float64 little endian. The payload starts
        // aligned, so no padding: 4 + 6 × 8 = 52 bytes.
        let t = Twist {
            linear: Vector3 {
                x: 1.0,
                y: -2.0,
                z: 0.0,
            },
            angular: Vector3 {
                x: 0.0,
                y: 0.0,
                z: 0.5,
            },
        };
        let b = to_cdr(&t).unwrap();
        let mut expected = vec![0x00, 0x01, 0x00, 0x00];
        // 1.0 = 0x3FF0000000000000, −2.0 = 0xC000000000000000, 0.5 = 0x3FE0000000000000;
        // little endian puts the exponent byte last.
        expected.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0xF0, 0x3F]);
        expected.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0x00, 0xC0]);
        expected.extend_from_slice(&[0; 8]);
        expected.extend_from_slice(&[0; 8]);
        expected.extend_from_slice(&[0; 8]);
        expected.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0xE0, 0x3F]);
        assert_eq!(b.len(), 52);
        assert_eq!(b, expected);
    }

    #[test]
    fn header_golden_bytes() {
        // stamp.sec = 1 (int32 LE 01 00 00 00), stamp.nanosec = 500_000_000 = 0x1DCD6500
        // (LE 00 65 CD 1D), frame_id "odom": length 5 including the NUL (05 00 00 00), the
        // four bytes and 00. 4 + 4 + 4 + 4 + 5 = 21 bytes.
        let h = Header::new(1_500_000_000, "odom");
        let b = to_cdr(&h).unwrap();
        let expected = [
            0x00, 0x01, 0x00, 0x00, // encapsulation
            0x01, 0x00, 0x00, 0x00, // sec
            0x00, 0x65, 0xCD, 0x1D, // nanosec
            0x05, 0x00, 0x00, 0x00, // string length incl. NUL
            b'o', b'd', b'o', b'm', 0x00,
        ];
        assert_eq!(b, expected);
    }

    #[test]
    fn odometry_alignment_pads_the_float64_after_the_strings() {
        // header: sec(4) nanosec(4) len(4) "odom\0"(5) → 17 bytes; child_frame_id: pad to 20,
        // len(4) "base_link\0"(10) → 34; the first float64 is aligned to 8 → 40.
        let mut o = Odometry {
            header: Header::new(0, "odom"),
            child_frame_id: "base_link".into(),
            ..Default::default()
        };
        o.pose.pose.position.x = 3.0;
        o.pose.covariance[35] = 0.25;
        let b = to_cdr(&o).unwrap();
        let x = f64::from_le_bytes(b[4 + 40..4 + 48].try_into().unwrap());
        assert_eq!(x, 3.0);
        // pose: 7 float64 + 36 covariance; twist: 6 + 36 → (7 + 36 + 6 + 36) × 8 = 680.
        assert_eq!(b.len(), 4 + 40 + 680);
        let last_pose_cov = 4 + 40 + (7 + 35) * 8;
        assert_eq!(
            f64::from_le_bytes(b[last_pose_cov..last_pose_cov + 8].try_into().unwrap()),
            0.25
        );
        round_trip(&o);
    }

    #[test]
    fn round_trips_of_every_type() {
        round_trip(&Time::from_ns(1_700_000_000_123_456_789));
        round_trip(&Header::new(42, "base_link"));
        let mut cov = [0.0; 36];
        for (i, c) in cov.iter_mut().enumerate() {
            *c = i as f64 * 0.5;
        }
        round_trip(&Odometry {
            header: Header::new(5, "odom"),
            child_frame_id: "base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose {
                    position: Point {
                        x: 1.0,
                        y: 2.0,
                        z: 0.0,
                    },
                    orientation: Quaternion::from_yaw(0.3),
                },
                covariance: cov,
            },
            twist: TwistWithCovariance {
                twist: Twist::default(),
                covariance: cov,
            },
        });
        round_trip(&TwistStamped {
            header: Header::new(7, "base_link"),
            twist: Twist {
                linear: Vector3 {
                    x: 0.1,
                    y: 0.2,
                    z: 0.0,
                },
                angular: Vector3::default(),
            },
        });
        round_trip(&TFMessage {
            transforms: vec![
                TransformStamped {
                    header: Header::new(1, "odom"),
                    child_frame_id: "base_link".into(),
                    transform: Transform {
                        translation: Vector3 {
                            x: 1.0,
                            y: 0.0,
                            z: 0.0,
                        },
                        rotation: Quaternion::from_yaw(1.0),
                    },
                };
                2
            ],
        });
        round_trip(&JointState {
            header: Header::new(1, ""),
            name: vec!["a".into(), "bb".into()],
            position: vec![1.0, 2.0],
            velocity: vec![0.5, -0.5],
            effort: vec![],
        });
        round_trip(&DiagnosticArray {
            header: Header::new(3, ""),
            status: vec![DiagnosticStatus {
                level: DiagnosticStatus::WARN,
                name: "rollbase: wheel 1".into(),
                message: "late feedback".into(),
                hardware_id: "node 1".into(),
                values: vec![KeyValue {
                    key: "late".into(),
                    value: "3".into(),
                }],
            }],
        });
        round_trip(&StringMsg {
            data: "tracking".into(),
        });
        round_trip(&Float64MultiArray {
            layout: MultiArrayLayout {
                dim: vec![MultiArrayDimension {
                    label: "legs".into(),
                    size: 4,
                    stride: 4,
                }],
                data_offset: 0,
            },
            data: vec![0.4, 0.41, 0.42, 0.43],
        });
        round_trip(&TriggerRequest::default());
        round_trip(&TriggerResponse {
            success: true,
            message: "ok".into(),
        });
        round_trip(&CanFrame {
            header: Header::new(9, "can0"),
            id: 0x181,
            dlc: 3,
            data: [1, 2, 3, 0, 0, 0, 0, 0],
            ..Default::default()
        });
        round_trip(&Icr {
            header: Header::new(1, "base_link"),
            cycle: 12,
            at_infinity: false,
            icr_x: 0.5,
            icr_y: -1.0,
            active: true,
            min_distance: 0.3,
            nearest_wheel: 2,
            d_start: vec![0.25; 4],
            deviation: vec![0.0; 7],
            wheel_x: vec![0.3; 4],
            wheel_y: vec![0.2; 4],
        });
    }

    #[test]
    fn big_endian_payloads_decode() {
        // Header 00 00 = CDR_BE; Vector3 (1, 2, 3) big endian.
        let mut b = vec![0x00, 0x00, 0x00, 0x00];
        for x in [1.0f64, 2.0, 3.0] {
            b.extend_from_slice(&x.to_be_bytes());
        }
        let v: Vector3 = from_cdr(&b).unwrap();
        assert_eq!(
            v,
            Vector3 {
                x: 1.0,
                y: 2.0,
                z: 3.0
            }
        );
    }

    #[test]
    fn bad_bytes_are_typed_errors_naming_the_type() {
        for bad in [&[][..], &[0, 1, 0][..], &[0x00, 0x07, 0, 0, 1, 2][..]] {
            let e = from_cdr::<Twist>(bad).unwrap_err();
            assert!(e.to_string().contains("geometry_msgs/msg/Twist"), "{e}");
        }
        // Truncated payload.
        let b = to_cdr(&Twist::default()).unwrap();
        let e = from_cdr::<Twist>(&b[..20]).unwrap_err();
        assert!(matches!(e, MsgError::Decode { len: 20, .. }), "{e}");
        // A sequence claiming 4 billion elements ends at the end of the data.
        let mut s = CDR_LE_HEADER.to_vec();
        s.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(from_cdr::<TFMessage>(&s).is_err());
    }

    #[test]
    fn dds_names_and_full_definitions() {
        assert_eq!(TWIST.dds_type_name(), "geometry_msgs::msg::dds_::Twist_");
        assert_eq!(ODOMETRY.dds_type_name(), "nav_msgs::msg::dds_::Odometry_");
        assert_eq!(
            TRIGGER_REQUEST.dds_type_name(),
            "std_srvs::srv::dds_::Trigger_Request_"
        );
        let sep = "=".repeat(80);
        let full = ODOMETRY.full_definition();
        assert!(full.starts_with("std_msgs/Header header\nstring child_frame_id\n"));
        // Each dependency exactly once, after a separator line.
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
            let line = format!("{sep}\nMSG: {dep}\n");
            assert_eq!(full.matches(&line).count(), 1, "{dep} in\n{full}");
        }
        assert_eq!(full.matches(&sep).count(), 9);
        assert_eq!(TIME.full_definition(), "int32 sec\nuint32 nanosec\n");
    }
}
