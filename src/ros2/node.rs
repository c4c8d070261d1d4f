//! The `rollbase` ROS 2 node: subscribes velocity and leg commands, serves `~/stop` and
//! `~/rearm`, publishes odometry, tf, joint states, diagnostics, the supervisor state and the
//! robot model, and announces itself to `ros2 node list`.
//!
//! It runs on two threads of its own, never on the cycle thread:
//!
//! - `rollbase-ros2-cmd` runs the node's async side on a single-threaded executor: the
//!   command readers, the services, the discovery announcement and the participant's status
//!   events (incompatible QoS). Every command becomes a [`CommandEvent`] stamped with the
//!   time since `origin` and goes out with `try_send`: a full command queue drops it, counts
//!   it ([`NodeStats`]) and logs it (once per second at most).
//! - `rollbase-ros2-pub` takes [`BaseState`] values from the state channel (one per cycle) and
//!   publishes decimated ([`super::convert::Decimator`], on cycle time). The cycle hands states
//!   over with `try_send` on a bounded channel, so a slow DDS peer can make this thread drop
//!   states, never delay a cycle.
//!
//! QoS (see docs/ros2.md): published topics and services reliable, volatile, keep last 10
//! (ROS 2's defaults); the `cmd_vel` and leg command readers best effort (they match
//! reliable and best-effort publishers; see [`qos::any_publisher`], [`qos::leg_commands`]);
//! `robot_description` and `ros_discovery_info` reliable, transient
//! local, keep last 1. A sample that does not decode, on any endpoint, is counted for that endpoint and
//! logged the first time with the reason; an incompatible-QoS event is logged with the policy.
//!
//! The node stops when the [`NodeHandle`] is dropped or shut down, or when the state
//! channel's sender is dropped (then only the command side keeps running until shutdown).

use super::convert::{self, StateSampler};
use super::dds::{self, qos, Dds, MsgWriter, RawPayload, RawReader, RawWriter};
use super::discovery::{self, GidLayout, NodeEntities, ParticipantEntities};
use super::msg::{
    self, DiagnosticArray, Float64MultiArray, JointState, Odometry, RosMsg, StringMsg, TFMessage,
    TriggerRequest, TriggerResponse, Twist, TwistStamped,
};
use super::params;
use super::service::{self, RequestMeta};
use super::{Ros2Error, Ros2Options, ServiceMapping};
use futures::{FutureExt, StreamExt};
use rollbase_control::runtime::CommandSender;
use rollbase_control::service::ports::{BaseState, CommandEvent, CommandKind};
use rustdds::{
    DataReaderStatus, DomainParticipantStatusEvent, QosPolicies, RTPSEntity, SampleIdentity,
    SequenceNumber, StatusEvented, Timestamp, WriteOptionsBuilder, GUID,
};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Counters of a running node (shared with its threads; read them any time).
#[derive(Debug, Default)]
pub struct NodeStats {
    /// Commands passed to the command port.
    pub commands_sent: AtomicU64,
    /// Commands dropped because the command queue was full.
    pub commands_dropped: AtomicU64,
    /// Commands refused by the node before the port (TwistStamped in a foreign frame).
    pub commands_refused: AtomicU64,
    /// Samples that could not be decoded, on any endpoint (per endpoint: [`Self::undecodable`]).
    pub receive_errors: AtomicU64,
    /// States taken from the state channel.
    pub states: AtomicU64,
    /// Messages published.
    pub published: AtomicU64,
    /// Publications that failed (e.g. a reliable reader not acknowledging in time).
    pub publish_errors: AtomicU64,
    /// Service requests answered (both mappings).
    pub services_answered: AtomicU64,
    /// Of those, answered in the rmw_cyclonedds mapping.
    pub services_cyclone: AtomicU64,
    /// Of those, answered in the enhanced (rmw_fastrtps) mapping.
    pub services_enhanced: AtomicU64,
    /// Incompatible-QoS events (a peer's endpoint that cannot match one of ours).
    pub qos_incompatible: AtomicU64,
    /// Undecodable samples per endpoint (`/cmd_vel`, `/rollbase/stop`, …).
    pub undecodable: Mutex<BTreeMap<String, u64>>,
    /// Samples DDS dropped unread on a command endpoint (`/cmd_vel`, `/leg_commands`) because
    /// they announced more than rustdds's fragment cap (256 KiB, vendor/rustdds/PATCHES.md).
    pub oversized: Mutex<BTreeMap<String, u64>>,
    /// The `ros_discovery_info` layout announced (`None`: not yet known).
    pub discovery_layout: Mutex<Option<GidLayout>>,
}

impl NodeStats {
    fn add(c: &AtomicU64) {
        c.fetch_add(1, Ordering::Relaxed);
    }

    /// Undecodable samples per endpoint, as a copy.
    pub fn undecodable_by_endpoint(&self) -> BTreeMap<String, u64> {
        self.undecodable
            .lock()
            .map(|g| g.clone())
            .unwrap_or_default()
    }

    /// Oversized samples dropped per endpoint, as a copy.
    pub fn oversized_by_endpoint(&self) -> BTreeMap<String, u64> {
        self.oversized.lock().map(|g| g.clone()).unwrap_or_default()
    }

    /// The announced discovery layout.
    pub fn announced_layout(&self) -> Option<GidLayout> {
        self.discovery_layout.lock().ok().and_then(|g| *g)
    }
}

/// A running node. Dropping it (or [`NodeHandle::shutdown`]) stops the node's threads and
/// leaves the DDS domain.
pub struct NodeHandle {
    stop: Arc<AtomicBool>,
    wake: Option<futures::channel::oneshot::Sender<()>>,
    threads: Vec<JoinHandle<()>>,
    stats: Arc<NodeStats>,
    domain_id: u16,
}

impl NodeHandle {
    /// The node's counters.
    pub fn stats(&self) -> &NodeStats {
        &self.stats
    }

    /// The DDS domain the node joined.
    pub fn domain_id(&self) -> u16 {
        self.domain_id
    }

    /// Stops the node and waits for its threads (at most about 100 ms after the call for the
    /// publishing thread; the command thread ends at once).
    pub fn shutdown(mut self) {
        self.stop_threads();
    }

    fn stop_threads(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(w) = self.wake.take() {
            let _ = w.send(());
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for NodeHandle {
    fn drop(&mut self) {
        self.stop_threads();
    }
}

/// Rate-limited logging of drops (at most one line per second per kind).
struct DropLog {
    last: Option<Instant>,
    suppressed: u64,
}

impl DropLog {
    fn new() -> Self {
        Self {
            last: None,
            suppressed: 0,
        }
    }

    fn log(&mut self, what: &str) {
        let now = Instant::now();
        match self.last {
            Some(l) if now.duration_since(l) < Duration::from_secs(1) => self.suppressed += 1,
            _ => {
                let more = if self.suppressed > 0 {
                    format!(" ({} more since the last report)", self.suppressed)
                } else {
                    String::new()
                };
                tracing::warn!("ros2: {what}{more}");
                self.last = Some(now);
                self.suppressed = 0;
            }
        }
    }
}

/// The state the services report in their answers.
type SharedState = Arc<Mutex<Option<String>>>;

/// What a service does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ServiceKind {
    /// `~/stop`.
    Stop,
    /// `~/rearm`.
    Rearm,
    /// A parameter service: index into [`params::SERVICES`].
    Param(usize),
}

/// A service's two DDS endpoints.
struct ServiceEndpoints {
    name: String,
    kind: ServiceKind,
    requests: RawReader,
    replies: RawWriter,
}

fn service(
    dds: &Dds,
    absolute: &str,
    kind: ServiceKind,
    req: &msg::MsgDef,
    rep: &msg::MsgDef,
) -> Result<ServiceEndpoints, Ros2Error> {
    let (rq, rr) = dds::service_dds_names(absolute);
    Ok(ServiceEndpoints {
        name: absolute.to_string(),
        kind,
        requests: dds.raw_reader(&rq, &req.dds_type_name(), qos::ros_default())?,
        replies: dds.raw_writer(&rr, &rep.dds_type_name(), qos::ros_default())?,
    })
}

/// A reply ready to write: payload, related identity, mapping.
type Reply = (Vec<u8>, Option<service::SampleId>, ServiceMapping);

/// Decodes a request of `Req` in the caller's mapping, answers it with `f`, encodes the reply.
fn serve<Req: RosMsg, Resp: RosMsg>(
    s: &dds::RawSample,
    meta: &dds::SampleMeta,
    mapping: ServiceMapping,
    f: impl FnOnce(&Req) -> Resp,
) -> Result<Reply, String> {
    let req = service::decode_request::<Req>(
        &s.payload,
        s.big_endian,
        &RequestMeta {
            writer_guid: meta.writer_guid,
            sequence_number: meta.sequence_number,
            related: meta.related,
        },
        mapping,
    )?;
    let resp = f(&req.request);
    let (bytes, related) =
        service::encode_reply(&resp, &req.reply_to).map_err(|e| e.to_string())?;
    Ok((bytes, related, req.reply_to.mapping()))
}

/// The node's endpoints by GUID, for messages about them and for its announcement.
#[derive(Default)]
struct Endpoints {
    names: BTreeMap<GUID, String>,
    readers: Vec<[u8; 16]>,
    writers: Vec<[u8; 16]>,
}

impl Endpoints {
    fn reader(&mut self, g: GUID, what: String) {
        self.readers.push(g.to_bytes());
        self.names.insert(g, what);
    }
    fn writer(&mut self, g: GUID, what: String) {
        self.writers.push(g.to_bytes());
        self.names.insert(g, what);
    }
}

/// Starts the node: joins the DDS domain (`opts.domain_id`, else `ROS_DOMAIN_ID`, else 0),
/// creates every topic and service, and starts the node's threads.
///
/// - `cmd_tx`: the command port's channel; the node `try_send`s into it and never blocks
///   (`~/stop` and `~/rearm` take its priority lane: never dropped behind velocity commands).
/// - `state_rx`: one [`BaseState`] per cycle; the node publishes decimated to its rates.
/// - `origin`: the instant the driver was ready; command times are seconds since then.
///
/// Everything that can fail is created before this returns: an error means nothing runs.
pub fn spawn_node(
    opts: Ros2Options,
    cmd_tx: CommandSender,
    state_rx: Receiver<BaseState>,
    origin: Instant,
) -> Result<NodeHandle, Ros2Error> {
    opts.validate(None)?;
    let domain = opts.resolve_domain_id()?;
    let dds = Dds::new(domain, &opts.only_addresses)?;
    let mut eps = Endpoints::default();

    // Publishers.
    let pubw = |name: &str| opts.topic(name);
    let odom_pub = dds.writer::<Odometry>(&pubw("odom"), qos::ros_default())?;
    eps.writer(odom_pub.guid(), format!("publisher {}", pubw("odom")));
    let tf_pub = if opts.publish_tf {
        let w = dds.writer::<TFMessage>(&pubw("tf"), qos::ros_default())?;
        eps.writer(w.guid(), format!("publisher {}", pubw("tf")));
        Some(w)
    } else {
        None
    };
    let joints_pub = dds.writer::<JointState>(&pubw("joint_states"), qos::ros_default())?;
    eps.writer(
        joints_pub.guid(),
        format!("publisher {}", pubw("joint_states")),
    );
    let diag_pub = dds.writer::<DiagnosticArray>(&pubw("diagnostics"), qos::ros_default())?;
    eps.writer(
        diag_pub.guid(),
        format!("publisher {}", pubw("diagnostics")),
    );
    let state_pub = dds.writer::<StringMsg>(&pubw("supervisor_state"), qos::ros_default())?;
    eps.writer(
        state_pub.guid(),
        format!("publisher {}", pubw("supervisor_state")),
    );
    let description_pub = match &opts.robot_description {
        Some(urdf) => {
            let topic = pubw("robot_description");
            let w = dds.writer::<StringMsg>(&topic, qos::latched())?;
            eps.writer(w.guid(), format!("publisher {topic}"));
            // Transient local: every subscriber that joins later gets it too.
            w.write(StringMsg { data: urdf.clone() }, None)
                .map_err(|e| Ros2Error::Entity {
                    what: "publication",
                    name: topic.clone(),
                    message: format!("{e:?}"),
                })?;
            Some(w)
        }
        None => None,
    };

    // cmd_vel and leg commands: a best-effort reader takes reliable and best-effort
    // publishers alike (see `qos::leg_commands`).
    let vel_topic = opts.topic(&opts.cmd_vel_topic);
    let vel_type = if opts.cmd_vel_stamped {
        TwistStamped::DEF
    } else {
        Twist::DEF
    };
    let cmd_vel = dds.raw_reader(
        &dds::topic_dds_name(&vel_topic),
        &vel_type.dds_type_name(),
        qos::any_publisher(),
    )?;
    eps.reader(cmd_vel.guid(), format!("subscription {vel_topic}"));
    let leg_topic = opts.topic(&opts.leg_topic);
    let legs = dds.raw_reader(
        &dds::topic_dds_name(&leg_topic),
        &Float64MultiArray::DEF.dds_type_name(),
        qos::leg_commands(),
    )?;
    eps.reader(legs.guid(), format!("subscription {leg_topic}"));
    let fqn = opts.node_fqn();
    let (tq, tr) = (&msg::TRIGGER_REQUEST, &msg::TRIGGER_RESPONSE);
    let mut services = vec![
        service(&dds, &format!("{fqn}/stop"), ServiceKind::Stop, tq, tr)?,
        service(&dds, &format!("{fqn}/rearm"), ServiceKind::Rearm, tq, tr)?,
    ];
    for (i, (name, rq, rp)) in params::SERVICES.iter().enumerate() {
        let abs = format!("{fqn}/{name}");
        services.push(service(&dds, &abs, ServiceKind::Param(i), rq, rp)?);
    }
    for s in &services {
        eps.reader(s.requests.guid(), format!("service {} (requests)", s.name));
        eps.writer(s.replies.guid(), format!("service {} (replies)", s.name));
    }

    // The node's announcement (ros_discovery_info) and the peers'.
    let announce_w = dds.raw_writer(discovery::TOPIC, discovery::TYPE_NAME, qos::latched())?;
    // Keyless: every peer's announcement is one instance; keep more than the last one.
    let announce_r = dds.raw_reader(
        discovery::TOPIC,
        discovery::TYPE_NAME,
        rustdds::QosPolicyBuilder::new()
            .reliability(rustdds::policy::Reliability::Reliable {
                max_blocking_time: rustdds::Duration::from_millis(100),
            })
            .durability(rustdds::policy::Durability::TransientLocal)
            .history(rustdds::policy::History::KeepLast { depth: 32 })
            .build(),
    )?;
    let me = ParticipantEntities {
        gid: dds.guid().to_bytes(),
        nodes: vec![NodeEntities {
            namespace: opts.namespace.clone(),
            name: opts.node_name.clone(),
            readers: eps.readers.clone(),
            writers: eps.writers.clone(),
        }],
    };
    let ros_distro = std::env::var("ROS_DISTRO").ok();
    let (layout, warning) = discovery::choose_layout(opts.distro, ros_distro.as_deref());
    if let Some(w) = warning {
        tracing::warn!("ros2: {w}");
    }

    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(NodeStats::default());
    let shared: SharedState = Arc::new(Mutex::new(None));
    let (wake_tx, wake_rx) = futures::channel::oneshot::channel::<()>();

    let mut cmd_side = CommandSide {
        cmd_tx,
        origin,
        stats: stats.clone(),
        shared: shared.clone(),
        base_frame: opts.frames.base.clone(),
        cmd_vel_stamped: opts.cmd_vel_stamped,
        mapping: opts.service_mapping,
        drops: DropLog::new(),
        logged_endpoints: BTreeSet::new(),
        logged_qos: BTreeSet::new(),
        names: eps.names,
        vel_topic,
        leg_topic,
        logged_oversized: BTreeSet::new(),
        announcement: me,
        announce_w,
        layout: None,
        mixed_warned: false,
    };
    if let Some(l) = layout {
        cmd_side.announce(l, "from --ros2-distro or ROS_DISTRO");
    } else {
        tracing::info!(
            "ros2: ROS_DISTRO is not set: rollbase announces its node to `ros2 node list` once the first ROS 2 peer shows which release it runs (or give --ros2-distro)"
        );
    }
    let participant = dds.participant().clone();
    let cmd_thread = std::thread::Builder::new()
        .name("rollbase-ros2-cmd".into())
        .spawn(move || {
            futures::executor::block_on(
                cmd_side.run(dds, cmd_vel, legs, services, announce_r, wake_rx),
            )
        })
        .map_err(|source| Ros2Error::Thread {
            name: "rollbase-ros2-cmd",
            source,
        })?;

    let pub_side = PublishSide {
        opts,
        stats: stats.clone(),
        shared,
        odom_pub,
        tf_pub,
        joints_pub,
        diag_pub,
        state_pub,
        _description_pub: description_pub,
        _participant: participant,
    };
    let stop2 = stop.clone();
    let pub_thread = std::thread::Builder::new()
        .name("rollbase-ros2-pub".into())
        .spawn(move || pub_side.run(state_rx, &stop2));
    let mut handle = NodeHandle {
        stop,
        wake: Some(wake_tx),
        threads: vec![cmd_thread],
        stats,
        domain_id: domain,
    };
    match pub_thread {
        Ok(t) => handle.threads.push(t),
        Err(source) => {
            // Dropping the handle stops the command thread.
            return Err(Ros2Error::Thread {
                name: "rollbase-ros2-pub",
                source,
            });
        }
    }
    Ok(handle)
}

/// The policy an incompatible-QoS event is about, with both sides' values.
fn qos_detail(offered: &QosPolicies, requested: &QosPolicies) -> String {
    match offered.compliance_failure_wrt(requested) {
        Some(id) => {
            use rustdds::dds::qos::QosPolicyId as P;
            let sides = match id {
                P::Reliability => format!(
                    " (offered {:?}, requested {:?})",
                    offered.reliability(),
                    requested.reliability()
                ),
                P::Durability => format!(
                    " (offered {:?}, requested {:?})",
                    offered.durability(),
                    requested.durability()
                ),
                P::Deadline => format!(
                    " (offered {:?}, requested {:?})",
                    offered.deadline(),
                    requested.deadline()
                ),
                P::Liveliness => format!(
                    " (offered {:?}, requested {:?})",
                    offered.liveliness(),
                    requested.liveliness()
                ),
                _ => String::new(),
            };
            format!("policy {id:?}{sides}")
        }
        None => "a policy rustdds did not name".into(),
    }
}

struct CommandSide {
    cmd_tx: CommandSender,
    origin: Instant,
    stats: Arc<NodeStats>,
    shared: SharedState,
    base_frame: String,
    cmd_vel_stamped: bool,
    mapping: ServiceMapping,
    drops: DropLog,
    /// Endpoints whose first undecodable sample was logged.
    logged_endpoints: BTreeSet<String>,
    /// (endpoint, policy) pairs whose incompatible-QoS event was logged.
    logged_qos: BTreeSet<(GUID, String)>,
    names: BTreeMap<GUID, String>,
    vel_topic: String,
    leg_topic: String,
    /// Endpoints whose first oversized sample was logged.
    logged_oversized: BTreeSet<String>,
    announcement: ParticipantEntities,
    announce_w: RawWriter,
    layout: Option<GidLayout>,
    mixed_warned: bool,
}

impl CommandSide {
    /// Passes a command on; `false` when the queue was full (or closed).
    fn send(&mut self, kind: CommandKind) -> bool {
        let ev = CommandEvent {
            t: self.origin.elapsed().as_secs_f64(),
            kind,
        };
        match self.cmd_tx.try_send(ev) {
            Ok(()) => {
                NodeStats::add(&self.stats.commands_sent);
                true
            }
            Err(TrySendError::Full(_)) => {
                NodeStats::add(&self.stats.commands_dropped);
                let n = self.stats.commands_dropped.load(Ordering::Relaxed);
                self.drops
                    .log(&format!("command queue full: command dropped ({n} in all)"));
                false
            }
            Err(TrySendError::Disconnected(_)) => {
                NodeStats::add(&self.stats.commands_dropped);
                self.drops
                    .log("command port closed: the cycle no longer takes commands");
                false
            }
        }
    }

    /// Counts an undecodable sample on `endpoint`; the first one is logged with the reason.
    fn undecodable(&mut self, endpoint: &str, what: &str, reason: &str) {
        NodeStats::add(&self.stats.receive_errors);
        let n = match self.stats.undecodable.lock() {
            Ok(mut g) => {
                let c = g.entry(endpoint.to_string()).or_insert(0);
                *c += 1;
                *c
            }
            Err(_) => 0,
        };
        if self.logged_endpoints.insert(endpoint.to_string()) {
            tracing::warn!(
                "ros2: {endpoint}: a {what} did not decode and was dropped: {reason}. Further ones on this endpoint are counted, not logged (the count is in the node's summary line)"
            );
        } else {
            tracing::debug!("ros2: {endpoint}: undecodable {what} #{n}: {reason}");
        }
    }

    fn state_now(&self) -> String {
        match self.shared.lock().ok().and_then(|g| g.clone()) {
            Some(state) => state,
            None => "unknown (no state received yet)".into(),
        }
    }

    fn answer(&mut self, service: &str, queued: bool) -> TriggerResponse {
        let now = self.state_now();
        let (success, message) = match (service, queued) {
            ("stop", true) => (
                true,
                format!(
                    "stop passed to the cycle: controlled stop, then the platform holds until ~/rearm (state was: {now})"
                ),
            ),
            ("rearm", true) => (
                true,
                format!(
                    "rearm passed to the cycle: faults whose cause is gone are cleared, a cause that persists keeps the fault latched; watch supervisor_state (state was: {now})"
                ),
            ),
            (_, _) => (
                false,
                format!(
                    "{service} NOT passed on: the command queue is full or closed; try again (state: {now})"
                ),
            ),
        };
        TriggerResponse { success, message }
    }

    /// Writes the node's announcement in `layout` (once; later layouts only warn).
    fn announce(&mut self, layout: GidLayout, why: &str) {
        match self.layout {
            Some(l) if l == layout => {}
            Some(l) => {
                if !self.mixed_warned {
                    self.mixed_warned = true;
                    tracing::warn!(
                        "ros2: a peer announces its nodes with the {layout}, others with the {l}: ROS 2 releases do not mix in one domain; rollbase stays visible to the {l} peers"
                    );
                }
            }
            None => {
                let bytes = discovery::encode(&self.announcement, layout);
                match self.announce_w.write(RawPayload(bytes), None) {
                    Ok(()) => {
                        self.layout = Some(layout);
                        if let Ok(mut g) = self.stats.discovery_layout.lock() {
                            *g = Some(layout);
                        }
                        tracing::info!(
                            "ros2: node announced on ros_discovery_info with the {layout} ({why})"
                        );
                    }
                    Err(e) => tracing::warn!("ros2: announcing the node failed: {e:?}"),
                }
            }
        }
    }

    /// A status event of a command reader (`legs`: the leg reader).
    ///
    /// - A publisher matched or left (`SubscriptionMatched`): logged with the number now
    ///   matched, so that a user sees their teleop or Nav2 connect. The readers are best
    ///   effort: a sample a publisher writes before *this* side matched it is dropped by
    ///   rustdds (a DATA from a writer it does not know yet), even though the publisher's
    ///   side may already report the match. A publisher that streams loses only its first
    ///   samples; one that sends a single command should wait for this line.
    /// - A sample that rustdds dropped as larger than its fragment cap (`SampleLost`, which
    ///   the vendored rustdds reports for that alone) is counted for the endpoint and logged
    ///   once per endpoint.
    fn reader_status(&mut self, legs: bool, ev: DataReaderStatus) {
        let endpoint = if legs {
            self.leg_topic.clone()
        } else {
            self.vel_topic.clone()
        };
        let count = match ev {
            DataReaderStatus::SampleLost { count } => count,
            DataReaderStatus::SubscriptionMatched { current, .. } => {
                let what = if current.count_change() >= 0 {
                    "a publisher matched"
                } else {
                    "a publisher left"
                };
                tracing::info!("ros2: {endpoint}: {what} ({} matched now)", current.count());
                return;
            }
            _ => return,
        };
        // The reader's running total (an event lost to a full status channel loses no count).
        let total = u64::try_from(count.count()).unwrap_or(0);
        if let Ok(mut g) = self.stats.oversized.lock() {
            let c = g.entry(endpoint.clone()).or_insert(0);
            let new = total.saturating_sub(*c);
            *c = (*c).max(total);
            self.stats.receive_errors.fetch_add(new, Ordering::Relaxed);
        }
        if self.logged_oversized.insert(endpoint.clone()) {
            tracing::warn!(
                "ros2: {endpoint}: a publisher sent a sample larger than {} KiB (a command needs less than 1 KiB); DDS dropped it before reading it. Further ones on this endpoint are counted, not logged (the count is in the node's summary line)",
                dds::MAX_SAMPLE_BYTES / 1024
            );
        }
    }

    /// A velocity or leg command sample.
    fn command(&mut self, legs: bool, s: &dds::RawSample) {
        if legs {
            match dds::decode::<Float64MultiArray>(s) {
                Ok(m) => {
                    self.send(convert::legs_command(&m.data));
                }
                Err(e) => {
                    let ep = self.leg_topic.clone();
                    self.undecodable(&ep, "std_msgs/msg/Float64MultiArray", &e);
                }
            }
            return;
        }
        let decoded = if self.cmd_vel_stamped {
            dds::decode::<TwistStamped>(s).map(|m| (Some(m.header.frame_id), m.twist))
        } else {
            dds::decode::<Twist>(s).map(|m| (None, m))
        };
        match decoded {
            Ok((Some(f), _)) if !f.is_empty() && f != self.base_frame => {
                NodeStats::add(&self.stats.commands_refused);
                let base = self.base_frame.clone();
                self.drops.log(&format!(
                    "velocity command in frame {f:?} ignored: rollbase takes body twists in {base:?} (or an empty frame_id)"
                ));
            }
            Ok((_, twist)) => {
                self.send(convert::motion_command(&twist));
            }
            Err(e) => {
                let ep = self.vel_topic.clone();
                let ty = if self.cmd_vel_stamped {
                    TwistStamped::DEF.name
                } else {
                    Twist::DEF.name
                };
                self.undecodable(&ep, ty, &e);
            }
        }
    }

    /// A service request: decoded in the caller's mapping, carried out, answered likewise.
    async fn request(
        &mut self,
        srv: &ServiceEndpoints,
        dcc: rustdds::no_key::DeserializedCacheChange<dds::RawSample>,
    ) {
        let meta = dds::sample_meta(&dcc);
        let s = dcc.into_value();
        let m = self.mapping;
        let reply = match srv.kind {
            ServiceKind::Stop | ServiceKind::Rearm => {
                let (kind, which) = if srv.kind == ServiceKind::Stop {
                    (CommandKind::Stop, "stop")
                } else {
                    (CommandKind::Rearm, "rearm")
                };
                // Decoded before the command is passed on: an undecodable request does nothing.
                match service::decode_request::<TriggerRequest>(
                    &s.payload,
                    s.big_endian,
                    &RequestMeta {
                        writer_guid: meta.writer_guid,
                        sequence_number: meta.sequence_number,
                        related: meta.related,
                    },
                    m,
                ) {
                    Err(e) => Err(e),
                    Ok(_) => {
                        let queued = self.send(kind);
                        let resp = self.answer(which, queued);
                        serve::<TriggerRequest, TriggerResponse>(&s, &meta, m, |_| resp)
                    }
                }
            }
            ServiceKind::Param(0) => serve(&s, &meta, m, params::answer_list),
            ServiceKind::Param(1) => serve(&s, &meta, m, params::answer_get),
            ServiceKind::Param(2) => serve(&s, &meta, m, params::answer_types),
            ServiceKind::Param(3) => serve(&s, &meta, m, params::answer_describe),
            ServiceKind::Param(4) => serve(&s, &meta, m, params::answer_set),
            ServiceKind::Param(_) => serve(&s, &meta, m, params::answer_set_atomically),
        };
        let (bytes, related, mapping) = match reply {
            Ok(r) => r,
            Err(e) => {
                self.undecodable(&srv.name, "service request", &e);
                return;
            }
        };
        let mut wo = WriteOptionsBuilder::new().source_timestamp(Timestamp::now());
        if let Some((g, sn)) = related {
            wo = wo.related_sample_identity(SampleIdentity {
                writer_guid: GUID::from_bytes(g),
                sequence_number: SequenceNumber::from(sn),
            });
        }
        match srv
            .replies
            .async_write_with_options(RawPayload(bytes), wo.build())
            .await
        {
            Ok(_) => {
                NodeStats::add(&self.stats.services_answered);
                NodeStats::add(match mapping {
                    ServiceMapping::Enhanced => &self.stats.services_enhanced,
                    _ => &self.stats.services_cyclone,
                });
                tracing::debug!("ros2: {} answered in the {mapping:?} mapping", srv.name);
            }
            Err(e) => tracing::warn!("ros2: {}: the reply could not be sent: {e:?}", srv.name),
        }
    }

    /// A peer's `ros_discovery_info` sample: its layout decides ours (when not fixed yet).
    fn peer_announcement(&mut self, meta: &dds::SampleMeta, s: &dds::RawSample) {
        if meta.writer_guid[..12] == self.announcement.gid[..12] {
            return; // our own
        }
        if let Some((layout, p)) = discovery::detect_layout(&s.payload, s.big_endian) {
            let names: Vec<String> = p
                .nodes
                .iter()
                .map(|n| {
                    if n.namespace == "/" {
                        format!("/{}", n.name)
                    } else {
                        format!("{}/{}", n.namespace, n.name)
                    }
                })
                .collect();
            tracing::debug!("ros2: peer participant with nodes {names:?} ({layout})");
            self.announce(layout, "detected from a peer's announcement");
        }
    }

    /// A participant status event: incompatible QoS on one of our endpoints is logged (once
    /// per endpoint and policy) and counted.
    fn status(&mut self, ev: DomainParticipantStatusEvent) {
        let (local, remote, requested, offered, side) = match ev {
            DomainParticipantStatusEvent::RemoteWriterQosIncompatible {
                local_reader,
                remote_writer,
                requested_qos,
                offered_qos,
            } => (
                local_reader,
                remote_writer,
                requested_qos,
                offered_qos,
                "a publisher",
            ),
            DomainParticipantStatusEvent::RemoteReaderQosIncompatible {
                local_writer,
                remote_reader,
                requested_qos,
                offered_qos,
            } => (
                local_writer,
                remote_reader,
                requested_qos,
                offered_qos,
                "a subscriber",
            ),
            _ => return,
        };
        let Some(name) = self.names.get(&local).cloned() else {
            return;
        };
        NodeStats::add(&self.stats.qos_incompatible);
        let detail = qos_detail(&offered, &requested);
        if self.logged_qos.insert((local, detail.clone())) {
            tracing::warn!(
                "ros2: {name}: {side} ({:02x?}) has incompatible QoS, they do not match: {detail}",
                &remote.to_bytes()[..12]
            );
        }
    }

    async fn run(
        mut self,
        dds: Dds,
        cmd_vel: RawReader,
        legs: RawReader,
        services: Vec<ServiceEndpoints>,
        announcements: RawReader,
        wake: futures::channel::oneshot::Receiver<()>,
    ) {
        let mut wake = wake.fuse();
        let listener = dds.participant().status_listener();
        let status_s = listener.as_async_status_stream().fuse();
        futures::pin_mut!(status_s);
        // The streams borrow the readers: they end with this block.
        {
            let vel_s = cmd_vel.as_async_stream();
            let legs_s = legs.as_async_stream();
            // Every service's requests, tagged with the service's index.
            let mut requests_s =
                futures::stream::select_all(services.iter().enumerate().map(|(i, srv)| {
                    srv.requests
                        .as_async_stream()
                        .map(move |r| (i, r))
                        .boxed_local()
                }));
            let ann_s = announcements.as_async_stream();
            let vel_st = cmd_vel.as_async_status_stream().fuse();
            let legs_st = legs.as_async_status_stream().fuse();
            futures::pin_mut!(vel_s, legs_s, ann_s, vel_st, legs_st);
            'outer: loop {
                futures::select! {
                    _ = wake => break 'outer,
                    ev = status_s.next() => if let Some(ev) = ev {
                        // Status events only inform; if they ever end, commands go on.
                        self.status(ev);
                    },
                    ev = vel_st.next() => if let Some(ev) = ev {
                        self.reader_status(false, ev);
                    },
                    ev = legs_st.next() => if let Some(ev) = ev {
                        self.reader_status(true, ev);
                    },
                    v = vel_s.next() => match v {
                        Some(Ok(dcc)) => self.command(false, &dcc.into_value()),
                        Some(Err(e)) => {
                            let ep = self.vel_topic.clone();
                            self.undecodable(&ep, "velocity command", &e.to_string());
                        }
                        None => break 'outer,
                    },
                    l = legs_s.next() => match l {
                        Some(Ok(dcc)) => self.command(true, &dcc.into_value()),
                        Some(Err(e)) => {
                            let ep = self.leg_topic.clone();
                            self.undecodable(&ep, "leg command", &e.to_string());
                        }
                        None => break 'outer,
                    },
                    r = requests_s.next() => match r {
                        Some((i, Ok(dcc))) => self.request(&services[i], dcc).await,
                        Some((i, Err(e))) => {
                            let ep = services[i].name.clone();
                            self.undecodable(&ep, "service request", &e.to_string());
                        }
                        None => break 'outer,
                    },
                    a = ann_s.next() => match a {
                        Some(Ok(dcc)) => {
                            let meta = dds::sample_meta(&dcc);
                            self.peer_announcement(&meta, &dcc.into_value());
                        }
                        // Not ours to count: a peer's discovery data, not a message to us.
                        Some(Err(e)) => tracing::debug!("ros2: ros_discovery_info sample: {e}"),
                        None => break 'outer,
                    },
                }
            }
        }
        // Endpoints before their participant: rustdds reports an error for an endpoint
        // removed after its participant's event loop stopped.
        drop(self);
        drop(services);
        drop(cmd_vel);
        drop(legs);
        drop(announcements);
        drop(listener);
        drop(dds);
    }
}

struct PublishSide {
    opts: Ros2Options,
    stats: Arc<NodeStats>,
    shared: SharedState,
    odom_pub: MsgWriter<Odometry>,
    tf_pub: Option<MsgWriter<TFMessage>>,
    joints_pub: MsgWriter<JointState>,
    diag_pub: MsgWriter<DiagnosticArray>,
    state_pub: MsgWriter<StringMsg>,
    /// Kept for its transient-local sample.
    _description_pub: Option<MsgWriter<StringMsg>>,
    /// Keeps the participant alive while this thread publishes.
    _participant: rustdds::DomainParticipant,
}

impl PublishSide {
    fn count<E>(&self, r: Result<(), E>, errors: &mut DropLog, topic: &str) {
        match r {
            Ok(()) => NodeStats::add(&self.stats.published),
            Err(_) => {
                NodeStats::add(&self.stats.publish_errors);
                errors.log(&format!(
                    "publishing {topic} failed (a reader does not keep up)"
                ));
            }
        }
    }

    fn run(self, state_rx: Receiver<BaseState>, stop: &AtomicBool) {
        let mut sampler = StateSampler::new(&self.opts);
        let mut errors = DropLog::new();
        while !stop.load(Ordering::SeqCst) {
            let s = match state_rx.recv_timeout(Duration::from_millis(100)) {
                Ok(s) => s,
                Err(RecvTimeoutError::Timeout) => continue,
                Err(RecvTimeoutError::Disconnected) => break,
            };
            NodeStats::add(&self.stats.states);
            if let Ok(mut g) = self.shared.lock() {
                *g = Some(convert::supervisor_text(&s).data);
            }
            let m = sampler.sample(&s);
            if let Some(w) = m.warning {
                tracing::warn!("ros2: {w}");
            }
            if let Some(o) = m.odom {
                let r = self.odom_pub.write(o, None);
                self.count(r.map_err(drop), &mut errors, "odom");
            }
            if let (Some(t), Some(p)) = (m.tf, &self.tf_pub) {
                let r = p.write(t, None);
                self.count(r.map_err(drop), &mut errors, "tf");
            }
            if let Some(j) = m.joint_states {
                let r = self.joints_pub.write(j, None);
                self.count(r.map_err(drop), &mut errors, "joint_states");
            }
            if let Some(d) = m.diagnostics {
                let r = self.diag_pub.write(d, None);
                self.count(r.map_err(drop), &mut errors, "diagnostics");
            }
            if let Some(t) = m.supervisor_state {
                let r = self.state_pub.write(t, None);
                self.count(r.map_err(drop), &mut errors, "supervisor_state");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_control::supervisor::SupervisorState;

    const CHILD_ENV: &str = "ROLLBASE_TEST_IN_NETNS";
    const TEST_NAME: &str = "ros2::node::tests::node_talks_to_a_rustdds_peer_in_a_private_netns";

    /// Whether this process's network namespace has no interface but loopback.
    fn only_loopback() -> bool {
        std::fs::read_to_string("/proc/net/dev")
            .map(|s| {
                s.lines()
                    .skip(2)
                    .filter_map(|l| l.split(':').next())
                    .all(|i| i.trim() == "lo")
            })
            .unwrap_or(false)
    }

    /// DDS discovery multicasts, so this test never starts DDS in the caller's network: it
    /// re-executes itself in a private network namespace (`unshare -n`, needs root or user
    /// namespaces) whose only interface is loopback, and says "skipped" when it cannot.
    #[test]
    fn node_talks_to_a_rustdds_peer_in_a_private_netns() {
        if std::env::var(CHILD_ENV).is_ok() {
            assert!(
                only_loopback(),
                "the child must run in a loopback-only namespace"
            );
            in_namespace();
            return;
        }
        let exe = std::env::current_exe().unwrap();
        let probe = std::process::Command::new("unshare")
            .args(["-n", "true"])
            .output();
        if !matches!(probe, Ok(ref o) if o.status.success()) {
            eprintln!("skipped: cannot create a network namespace (unshare -n needs root or user namespaces)");
            return;
        }
        let out = std::process::Command::new("unshare")
            .args([
                "-n",
                "sh",
                "-c",
                "ip link set lo up && exec \"$0\" --exact \"$1\" --nocapture --test-threads 1",
            ])
            .arg(&exe)
            .arg(TEST_NAME)
            .env(CHILD_ENV, "1")
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        if !out.status.success() && text.contains("ip: not found") {
            eprintln!("skipped: no `ip` command to bring up loopback in the namespace");
            return;
        }
        assert!(out.status.success(), "child failed:\n{text}");
        assert!(text.contains("1 passed"), "the child ran the test:\n{text}");
    }

    fn in_namespace() {
        let opts = Ros2Options {
            namespace: "/nstest".into(),
            ..Default::default()
        };
        // A command queue of 1 that is not drained until the end: the second command is dropped.
        let (cmd_tx, cmd_rx) = rollbase_control::runtime::command_channel(1, 1);
        let (state_tx, state_rx) = std::sync::mpsc::sync_channel::<BaseState>(8);
        let origin = Instant::now();
        let node = spawn_node(opts, cmd_tx, state_rx, origin).expect("node starts");

        let peer = Dds::new(0, &[]).unwrap();
        let twist_pub = peer
            .writer::<Twist>("/nstest/cmd_vel", qos::ros_default())
            .unwrap();
        let odom_sub = peer
            .reader::<Odometry>("/nstest/odom", qos::ros_default())
            .unwrap();

        let deadline = Instant::now() + Duration::from_secs(20);
        let mut k = 0u64;
        let mut odom = None;
        let mut sent = 0;
        while Instant::now() < deadline
            && (odom.is_none() || node.stats().commands_dropped.load(Ordering::Relaxed) == 0)
        {
            let mut s = BaseState {
                cycle: k,
                t: k as f64 * 0.004,
                log_time_ns: 1_000_000_000 + k * 4_000_000,
                n: 4,
                state: SupervisorState::Tracking,
                ..Default::default()
            };
            s.odometry.pose.x = 1.5;
            let _ = state_tx.try_send(s);
            k += 1;
            if let Ok(Some(o)) = odom_sub.take() {
                odom = Some(o);
            }
            // Once the peer sees the node, send commands until one is dropped.
            if odom.is_some() && sent < 50 && k.is_multiple_of(10) {
                let mut t = Twist::default();
                t.linear.x = 0.25 + sent as f64;
                if twist_pub.write(t, None).is_ok() {
                    sent += 1;
                }
            }
            std::thread::sleep(Duration::from_millis(4));
        }
        let o = odom.expect("odometry reached the peer");
        assert_eq!(o.header.frame_id, "odom");
        assert_eq!(o.child_frame_id, "base_link");
        assert_eq!(o.pose.pose.position.x, 1.5);
        let mut taken = Vec::new();
        cmd_rx.take(1, |e| taken.push(e));
        let first = *taken.first().expect("a command reached the queue");
        match first.kind {
            // 0.25 + the index of the first command that found the subscription matched.
            CommandKind::Motion(m) => assert_eq!(m.twist.vx.fract(), 0.25, "{m:?}"),
            k => panic!("{k:?}"),
        }
        assert!(first.t > 0.0 && first.t < origin.elapsed().as_secs_f64());
        let st = node.stats();
        assert_eq!(st.commands_sent.load(Ordering::Relaxed), 1);
        assert!(
            st.commands_dropped.load(Ordering::Relaxed) >= 1,
            "a full queue drops and counts"
        );
        assert!(st.published.load(Ordering::Relaxed) > 0);
        node.shutdown();
    }
}
