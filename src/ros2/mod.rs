//! rollbase as a ROS 2 participant, with no ROS installation: `rustdds` (a pure-Rust DDS/RTPS
//! implementation) with the standard ROS 2 topic and type names, QoS and CDR encoding, so
//! rclcpp/rclpy nodes on any DDS-based rmw (Cyclone DDS, Fast DDS) see an ordinary node.
//!
//! - [`msg`]: the message types (serde in `.msg` order, definitions, CDR codec);
//! - [`convert`]: state port → messages, messages → command port (pure; shared with the
//!   recorder);
//! - [`dds`]: ROS 2 names, types and QoS on rustdds;
//! - [`service`]: service requests in either rmw's request/reply mapping (pure);
//! - [`discovery`]: `ros_discovery_info` in Humble's and Jazzy's layouts (pure);
//! - [`urdf`]: the robot model from the platform file (pure);
//! - [`params`]: the parameter services every ROS 2 node has (none to set; pure answers);
//! - [`node`]: the node on its own threads, [`spawn_node`].
//!
//! See `docs/ros2.md` for topics, frames, services, options, QoS and Nav2 settings.

pub mod convert;
pub mod dds;
pub mod discovery;
pub mod msg;
pub mod node;
pub mod params;
pub mod service;
pub mod urdf;

pub use discovery::{DistroChoice, GidLayout};

pub use convert::{Frames, JointNames};
pub use node::{spawn_node, NodeHandle, NodeStats};

use std::net::IpAddr;

/// Errors of the ROS 2 layer: each says what to do.
#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    /// An option value is not acceptable.
    #[error("ROS 2 option {option}: {message}")]
    Option {
        /// The option (as on the command line).
        option: &'static str,
        /// What is wrong and what is accepted.
        message: String,
    },
    /// `ROS_DOMAIN_ID` is set to something that is not a domain id.
    #[error("ROS_DOMAIN_ID={value:?} is not a DDS domain id: set it to an integer 0..=232 (ROS 2's default is 0) or unset it")]
    DomainId {
        /// The environment value.
        value: String,
    },
    /// The DDS participant could not be created.
    #[error("cannot start the DDS participant on domain {domain}: {message}; check that the network is up and UDP ports 7400 + 250·domain … are free, or pick another ROS_DOMAIN_ID")]
    Participant {
        /// Domain id.
        domain: u16,
        /// What rustdds reported.
        message: String,
    },
    /// A topic, publisher, subscription or service could not be created.
    #[error("cannot create the ROS 2 {what} {name}: {message}")]
    Entity {
        /// Kind of entity.
        what: &'static str,
        /// Its name.
        name: String,
        /// What rustdds reported.
        message: String,
    },
    /// A node thread could not be started.
    #[error("cannot start the ROS 2 node thread {name}: {source}")]
    Thread {
        /// Thread name.
        name: &'static str,
        /// The OS error.
        source: std::io::Error,
    },
}

/// How service requests and replies are mapped onto DDS topics. ROS 2's rmw layers differ:
/// rmw_cyclonedds puts a request header (client id, sequence number) in the payload,
/// rmw_fastrtps uses the RTPS related-sample-identity ("enhanced" mapping of the OMG
/// RPC-over-DDS specification). See [`service`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ServiceMapping {
    /// Per request, the caller's (the default): one node serves both kinds of caller.
    #[default]
    Auto,
    /// Only rmw_cyclonedds_cpp callers.
    Cyclone,
    /// Only rmw_fastrtps_cpp (and rmw_connextdds) callers.
    Enhanced,
}

impl std::str::FromStr for ServiceMapping {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "cyclone" | "cyclonedds" => Ok(Self::Cyclone),
            "enhanced" | "fastdds" | "fastrtps" => Ok(Self::Enhanced),
            _ => Err(format!(
                "{s:?}: use auto (each caller's, the default), cyclone (rmw_cyclonedds_cpp only) or enhanced (rmw_fastrtps_cpp only)"
            )),
        }
    }
}

/// Options of the ROS 2 node (and of the ROS 2 topics of recordings). Every field has a
/// default ([`Ros2Options::default`]); [`Ros2Args`] exposes them on a command line.
#[derive(Clone, Debug, PartialEq)]
pub struct Ros2Options {
    /// Node name (default `rollbase`).
    pub node_name: String,
    /// Namespace of the node and of its relative topic names (default `/`). Topics are
    /// relative (`odom`, `tf`, …), so `--ros2-namespace /robot1` gives `/robot1/odom`.
    pub namespace: String,
    /// DDS domain; `None` reads `ROS_DOMAIN_ID` (unset: 0).
    pub domain_id: Option<u16>,
    /// Odometry and base frames (REP 105: `odom` → `base_link`).
    pub frames: Frames,
    /// Publish the odom → base transform on `tf` (turn off when another node, e.g.
    /// robot_localization, fuses odometry and publishes that transform).
    pub publish_tf: bool,
    /// Velocity command topic (default `cmd_vel`).
    pub cmd_vel_topic: String,
    /// Subscribe `geometry_msgs/TwistStamped` instead of `Twist` on the velocity topic (Nav2
    /// publishes stamped commands when its `enable_stamped_cmd_vel` is true). Its
    /// `header.frame_id` must be empty or the base frame.
    pub cmd_vel_stamped: bool,
    /// Leg command topic (default `leg_commands`, `std_msgs/Float64MultiArray`: one target
    /// extension per wheel in m, controller order).
    pub leg_topic: String,
    /// Joint names of `joint_states`.
    pub joint_names: JointNames,
    /// Rate of `odom` and `tf` (Hz, default 50).
    pub odom_rate_hz: f64,
    /// Rate of `joint_states` (Hz, default 50).
    pub joint_states_rate_hz: f64,
    /// Rate of `diagnostics` and of `supervisor_state` when it does not change (Hz, default 1;
    /// a change of the supervisor state, fault reason or limiting cause is published at once,
    /// at most once per 0.1 s).
    pub diagnostics_rate_hz: f64,
    /// Service mapping of `~/stop` and `~/rearm` (default: each caller's).
    pub service_mapping: ServiceMapping,
    /// Which release's `ros_discovery_info` layout the node announces itself in (default:
    /// `ROS_DISTRO`, else the peers').
    pub distro: DistroChoice,
    /// The URDF published on `robot_description` (transient local), if any.
    pub robot_description: Option<String>,
    /// Restrict DDS discovery announcements and multicast to the interfaces with these
    /// addresses (empty: all interfaces). Not a firewall: sockets still bind the wildcard.
    pub only_addresses: Vec<IpAddr>,
}

impl Default for Ros2Options {
    fn default() -> Self {
        Self {
            node_name: "rollbase".into(),
            namespace: "/".into(),
            domain_id: None,
            frames: Frames::default(),
            publish_tf: true,
            cmd_vel_topic: "cmd_vel".into(),
            cmd_vel_stamped: false,
            leg_topic: "leg_commands".into(),
            joint_names: JointNames::Default,
            odom_rate_hz: 50.0,
            joint_states_rate_hz: 50.0,
            diagnostics_rate_hz: 1.0,
            service_mapping: ServiceMapping::Auto,
            distro: DistroChoice::Auto,
            robot_description: None,
            only_addresses: Vec::new(),
        }
    }
}

/// A topic or node name element: letters, digits, `_`, not starting with a digit, no `__`.
fn check_token(s: &str) -> bool {
    !s.is_empty()
        && !s.starts_with(|c: char| c.is_ascii_digit())
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !s.contains("__")
}

/// Validates a ROS 2 namespace (`/` or `/a/b`); `a/b` is taken as `/a/b`.
pub fn parse_namespace(s: &str) -> Result<String, String> {
    let ns = if s.starts_with('/') {
        s.to_string()
    } else {
        format!("/{s}")
    };
    let ns = if ns.len() > 1 {
        ns.trim_end_matches('/').to_string()
    } else {
        ns
    };
    if ns == "/" || ns[1..].split('/').all(check_token) {
        Ok(ns)
    } else {
        Err(format!(
            "{s:?} is not a ROS 2 namespace: use /, or /name[/name…] with names of letters, digits and _"
        ))
    }
}

/// Validates a relative topic name (`cmd_vel`, `base/cmd_vel`).
pub fn parse_topic(s: &str) -> Result<String, String> {
    if s.split('/').all(check_token) {
        Ok(s.to_string())
    } else {
        Err(format!(
            "{s:?} is not a relative ROS 2 topic name: use name[/name…] of letters, digits and _ (it is resolved in the node's namespace)"
        ))
    }
}

/// Validates a node name.
pub fn parse_node_name(s: &str) -> Result<String, String> {
    if check_token(s) {
        Ok(s.to_string())
    } else {
        Err(format!(
            "{s:?} is not a ROS 2 node name: letters, digits and _, not starting with a digit"
        ))
    }
}

/// Validates a tf frame id (non-empty, no whitespace, no leading `/`: tf2 rejects those).
pub fn parse_frame(s: &str) -> Result<String, String> {
    if s.is_empty() || s.starts_with('/') || s.chars().any(char::is_whitespace) {
        Err(format!(
            "{s:?} is not a tf2 frame id: non-empty, without spaces and without a leading /"
        ))
    } else {
        Ok(s.to_string())
    }
}

/// Validates a publishing rate in Hz: finite, > 0, at most 1000 (rates above the cycle rate
/// publish every cycle).
pub fn parse_rate(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(r) if r.is_finite() && r > 0.0 && r <= 1000.0 => Ok(r),
        _ => Err(format!(
            "{s:?} is not a rate: give Hz as a number in (0, 1000], e.g. 50"
        )),
    }
}

/// Parses joint names: a comma-separated list, three per wheel in the order steer, drive,
/// leg (`default` for the generated names).
pub fn parse_joint_names(s: &str) -> Result<JointNames, String> {
    if s == "default" {
        return Ok(JointNames::Default);
    }
    let names: Vec<String> = s.split(',').map(|x| x.trim().to_string()).collect();
    if let Some(bad) = names
        .iter()
        .find(|n| n.is_empty() || n.chars().any(|c| c.is_whitespace() || c == '"'))
    {
        return Err(format!(
            "joint name {bad:?} in {s:?}: names are non-empty and without spaces or quotes, comma-separated"
        ));
    }
    if !names.len().is_multiple_of(3) {
        return Err(format!(
            "{} joint names in {s:?}: give 3 per wheel (steer, drive, leg)",
            names.len()
        ));
    }
    Ok(JointNames::Custom(names))
}

/// Reads `ROS_DOMAIN_ID` (unset or empty: 0).
pub fn domain_id_from_env() -> Result<u16, Ros2Error> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(_) => Ok(0),
        Ok(v) if v.trim().is_empty() => Ok(0),
        Ok(v) => match v.trim().parse::<u16>() {
            Ok(d) if d <= 232 => Ok(d),
            _ => Err(Ros2Error::DomainId { value: v }),
        },
    }
}

/// The ROS 2 options on a command line (flatten into a command's arguments with
/// `#[command(flatten)]`); [`Ros2Args::to_options`] gives [`Ros2Options`].
#[derive(clap::Args, Clone, Debug, Default, PartialEq)]
pub struct Ros2Args {
    /// ROS 2 node name.
    #[arg(long = "ros2-node-name", value_name = "NAME", value_parser = parse_node_name)]
    pub node_name: Option<String>,
    /// ROS 2 namespace of the node and its topics (default /).
    #[arg(long = "ros2-namespace", value_name = "NS", value_parser = parse_namespace)]
    pub namespace: Option<String>,
    /// DDS domain id (default: $ROS_DOMAIN_ID, else 0).
    #[arg(long = "ros2-domain-id", value_name = "ID", value_parser = clap::value_parser!(u16).range(0..=232))]
    pub domain_id: Option<u16>,
    /// Odometry frame (default odom).
    #[arg(long = "ros2-odom-frame", value_name = "FRAME", value_parser = parse_frame)]
    pub odom_frame: Option<String>,
    /// Base frame (default base_link).
    #[arg(long = "ros2-base-frame", value_name = "FRAME", value_parser = parse_frame)]
    pub base_frame: Option<String>,
    /// Do not publish odom → base on tf (when e.g. robot_localization publishes it).
    #[arg(long = "ros2-no-tf")]
    pub no_tf: bool,
    /// Velocity command topic (default cmd_vel).
    #[arg(long = "ros2-cmd-vel-topic", value_name = "TOPIC", value_parser = parse_topic)]
    pub cmd_vel_topic: Option<String>,
    /// Take geometry_msgs/TwistStamped on the velocity topic (Nav2 with enable_stamped_cmd_vel).
    #[arg(long = "ros2-cmd-vel-stamped")]
    pub cmd_vel_stamped: bool,
    /// Leg command topic (std_msgs/Float64MultiArray, one extension per wheel in m; default
    /// leg_commands).
    #[arg(long = "ros2-leg-topic", value_name = "TOPIC", value_parser = parse_topic)]
    pub leg_topic: Option<String>,
    /// Joint names for joint_states: 3 per wheel (steer,drive,leg), comma-separated.
    #[arg(long = "ros2-joint-names", value_name = "NAMES", value_parser = parse_joint_names)]
    pub joint_names: Option<JointNames>,
    /// Rate of odom and tf in Hz (default 50).
    #[arg(long = "ros2-odom-rate", value_name = "HZ", value_parser = parse_rate)]
    pub odom_rate: Option<f64>,
    /// Rate of joint_states in Hz (default 50).
    #[arg(long = "ros2-joint-states-rate", value_name = "HZ", value_parser = parse_rate)]
    pub joint_states_rate: Option<f64>,
    /// Rate of diagnostics in Hz (default 1).
    #[arg(long = "ros2-diagnostics-rate", value_name = "HZ", value_parser = parse_rate)]
    pub diagnostics_rate: Option<f64>,
    /// Service mapping: auto (each caller's, default), cyclone (rmw_cyclonedds_cpp only) or
    /// enhanced (rmw_fastrtps_cpp only).
    #[arg(long = "ros2-service-mapping", value_name = "MAPPING")]
    pub service_mapping: Option<ServiceMapping>,
    /// ROS 2 release whose discovery layout to announce the node in: humble, iron, jazzy,
    /// kilted, rolling, or auto (default: $ROS_DISTRO, else the first ROS 2 peer's).
    #[arg(long = "ros2-distro", value_name = "RELEASE")]
    pub distro: Option<DistroChoice>,
    /// Announce DDS only on the interface with this address (repeatable; default all).
    #[arg(long = "ros2-address", value_name = "IP")]
    pub only_addresses: Vec<IpAddr>,
}

impl Ros2Args {
    /// The options these arguments give (defaults for the rest).
    pub fn to_options(&self) -> Ros2Options {
        let d = Ros2Options::default();
        Ros2Options {
            node_name: self.node_name.clone().unwrap_or(d.node_name),
            namespace: self.namespace.clone().unwrap_or(d.namespace),
            domain_id: self.domain_id,
            frames: Frames {
                odom: self.odom_frame.clone().unwrap_or(d.frames.odom),
                base: self.base_frame.clone().unwrap_or(d.frames.base),
            },
            publish_tf: !self.no_tf,
            cmd_vel_topic: self.cmd_vel_topic.clone().unwrap_or(d.cmd_vel_topic),
            cmd_vel_stamped: self.cmd_vel_stamped,
            leg_topic: self.leg_topic.clone().unwrap_or(d.leg_topic),
            joint_names: self.joint_names.clone().unwrap_or(d.joint_names),
            odom_rate_hz: self.odom_rate.unwrap_or(d.odom_rate_hz),
            joint_states_rate_hz: self.joint_states_rate.unwrap_or(d.joint_states_rate_hz),
            diagnostics_rate_hz: self.diagnostics_rate.unwrap_or(d.diagnostics_rate_hz),
            service_mapping: self.service_mapping.unwrap_or(d.service_mapping),
            distro: self.distro.unwrap_or(d.distro),
            robot_description: None,
            only_addresses: self.only_addresses.clone(),
        }
    }
}

impl Ros2Options {
    /// Checks every field (the parse helpers' rules) and, when `wheels` is given, that custom
    /// joint names fit that many wheels. [`spawn_node`] calls it without `wheels`.
    pub fn validate(&self, wheels: Option<usize>) -> Result<(), Ros2Error> {
        let opt = |option: &'static str, r: Result<(), String>| {
            r.map_err(|message| Ros2Error::Option { option, message })
        };
        opt(
            "--ros2-node-name",
            parse_node_name(&self.node_name).map(drop),
        )?;
        opt(
            "--ros2-namespace",
            parse_namespace(&self.namespace).and_then(|ns| {
                if ns == self.namespace {
                    Ok(())
                } else {
                    Err(format!("{:?}: write it as {ns:?}", self.namespace))
                }
            }),
        )?;
        opt(
            "--ros2-odom-frame",
            parse_frame(&self.frames.odom).map(drop),
        )?;
        opt(
            "--ros2-base-frame",
            parse_frame(&self.frames.base).map(drop),
        )?;
        if self.frames.odom == self.frames.base {
            return Err(Ros2Error::Option {
                option: "--ros2-base-frame",
                message: format!(
                    "the base frame equals the odometry frame {:?}: they must differ",
                    self.frames.odom
                ),
            });
        }
        opt(
            "--ros2-cmd-vel-topic",
            parse_topic(&self.cmd_vel_topic).map(drop),
        )?;
        opt("--ros2-leg-topic", parse_topic(&self.leg_topic).map(drop))?;
        if self.leg_topic == self.cmd_vel_topic {
            return Err(Ros2Error::Option {
                option: "--ros2-leg-topic",
                message: format!("{:?} is also the velocity topic", self.leg_topic),
            });
        }
        for (option, r) in [
            ("--ros2-odom-rate", self.odom_rate_hz),
            ("--ros2-joint-states-rate", self.joint_states_rate_hz),
            ("--ros2-diagnostics-rate", self.diagnostics_rate_hz),
        ] {
            opt(option, parse_rate(&r.to_string()).map(drop))?;
        }
        if let (Some(n), JointNames::Custom(_)) = (wheels, &self.joint_names) {
            opt("--ros2-joint-names", self.joint_names.names(n).map(drop))?;
        }
        if let Some(d) = self.domain_id {
            if d > 232 {
                return Err(Ros2Error::Option {
                    option: "--ros2-domain-id",
                    message: format!("{d}: DDS domain ids are 0..=232"),
                });
            }
        }
        Ok(())
    }

    /// The domain id to use: the option, else `ROS_DOMAIN_ID`, else 0.
    pub fn resolve_domain_id(&self) -> Result<u16, Ros2Error> {
        match self.domain_id {
            Some(d) => Ok(d),
            None => domain_id_from_env(),
        }
    }

    /// The node's fully qualified name (`/rollbase`, `/robot1/rollbase`); its services are
    /// under it (`~/stop` is `<fqn>/stop`).
    pub fn node_fqn(&self) -> String {
        self.topic(&self.node_name)
    }

    /// A topic's absolute name: the namespace joined with the relative name.
    pub fn topic(&self, relative: &str) -> String {
        if self.namespace == "/" {
            format!("/{relative}")
        } else {
            format!("{}/{relative}", self.namespace)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        ros2: Ros2Args,
    }

    #[test]
    fn defaults_are_rep_105_and_the_documented_rates() {
        let o = Ros2Options::default();
        assert_eq!(
            (o.frames.odom.as_str(), o.frames.base.as_str()),
            ("odom", "base_link")
        );
        assert_eq!(
            (
                o.odom_rate_hz,
                o.joint_states_rate_hz,
                o.diagnostics_rate_hz
            ),
            (50.0, 50.0, 1.0)
        );
        assert!(o.publish_tf && !o.cmd_vel_stamped);
        assert_eq!(o.service_mapping, ServiceMapping::Auto);
        assert_eq!(o.distro, DistroChoice::Auto);
        o.validate(Some(4)).unwrap();
        assert_eq!(Cli::parse_from(["x"]).ros2.to_options(), o);
        assert_eq!(o.topic("odom"), "/odom");
    }

    #[test]
    fn command_line_sets_every_option() {
        let c = Cli::parse_from([
            "x",
            "--ros2-namespace",
            "robot1/base",
            "--ros2-node-name",
            "base",
            "--ros2-domain-id",
            "7",
            "--ros2-odom-frame",
            "r1/odom",
            "--ros2-base-frame",
            "r1/base_link",
            "--ros2-no-tf",
            "--ros2-cmd-vel-stamped",
            "--ros2-leg-topic",
            "legs/commands",
            "--ros2-joint-names",
            "s1,d1,l1,s2,d2,l2",
            "--ros2-odom-rate",
            "100",
            "--ros2-diagnostics-rate",
            "0.5",
            "--ros2-service-mapping",
            "enhanced",
            "--ros2-distro",
            "humble",
            "--ros2-address",
            "127.0.0.1",
        ]);
        let o = c.ros2.to_options();
        assert_eq!(o.namespace, "/robot1/base");
        assert_eq!(o.topic("odom"), "/robot1/base/odom");
        assert_eq!(o.domain_id, Some(7));
        assert!(!o.publish_tf && o.cmd_vel_stamped);
        assert_eq!(o.leg_topic, "legs/commands");
        assert_eq!(o.odom_rate_hz, 100.0);
        assert_eq!(o.diagnostics_rate_hz, 0.5);
        assert_eq!(o.service_mapping, ServiceMapping::Enhanced);
        assert_eq!(o.distro, DistroChoice::Fixed(GidLayout::Gid24));
        assert_eq!(
            o.only_addresses,
            vec!["127.0.0.1".parse::<IpAddr>().unwrap()]
        );
        o.validate(Some(2)).unwrap();
        let e = o.validate(Some(4)).unwrap_err().to_string();
        assert!(
            e.contains("--ros2-joint-names") && e.contains("6 joint names given for 4 wheels"),
            "{e}"
        );
    }

    #[test]
    fn bad_values_are_refused_with_what_is_accepted() {
        for args in [
            ["x", "--ros2-odom-rate", "0"],
            ["x", "--ros2-odom-rate", "NaN"],
            ["x", "--ros2-namespace", "/a//b"],
            ["x", "--ros2-namespace", "/1abc"],
            ["x", "--ros2-base-frame", "/base_link"],
            ["x", "--ros2-joint-names", "a,b"],
            ["x", "--ros2-domain-id", "300"],
            ["x", "--ros2-service-mapping", "zenoh"],
            ["x", "--ros2-distro", "noetic"],
            ["x", "--ros2-cmd-vel-topic", "cmd vel"],
        ] {
            assert!(Cli::try_parse_from(args).is_err(), "{args:?}");
        }
        let o = Ros2Options {
            frames: Frames {
                odom: "x".into(),
                base: "x".into(),
            },
            ..Default::default()
        };
        assert!(o
            .validate(None)
            .unwrap_err()
            .to_string()
            .contains("must differ"));
        let o = Ros2Options {
            odom_rate_hz: f64::INFINITY,
            ..Default::default()
        };
        assert!(o
            .validate(None)
            .unwrap_err()
            .to_string()
            .contains("--ros2-odom-rate"));
    }
}
