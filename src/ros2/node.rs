//! The `rollbase` ROS 2 node: subscribes velocity and leg commands, serves `~/stop` and
//! `~/rearm`, publishes odometry, tf, joint states, diagnostics and the supervisor state.
//!
//! It runs on two threads of its own, never on the cycle thread:
//!
//! - `rollbase-ros2-cmd` runs the node's async side on a single-threaded executor: the
//!   ros2-client spinner (discovery bookkeeping), the command subscriptions and the services.
//!   Every command becomes a [`CommandEvent`] stamped with the time since `origin` and goes
//!   out with `try_send`: a full command queue drops it, counts it ([`NodeStats`]) and logs it
//!   (once per second at most).
//! - `rollbase-ros2-pub` takes [`BaseState`] values from the state channel (one per cycle) and
//!   publishes decimated ([`super::convert::Decimator`], on cycle time). The cycle hands states
//!   over with `try_send` on a bounded channel, so a slow DDS peer can make this thread drop
//!   states, never delay a cycle.
//!
//! QoS of every topic and service: reliable, volatile, keep last 10, as ROS 2's
//! `rmw_qos_profile_default` and `rmw_qos_profile_services_default` (the library's own
//! subscription default is best effort, keep last 1, which ROS 2's reliable subscribers do not
//! match).
//!
//! The node stops when the [`NodeHandle`] is dropped or shut down, or when the state
//! channel's sender is dropped (then only the command side keeps running until shutdown).

use super::convert::{self, StateSampler};
use super::msg::{
    self, DiagnosticArray, Float64MultiArray, JointState, Odometry, RosMsg, StringMsg, TFMessage,
    TriggerRequest, TriggerResponse, Twist, TwistStamped,
};
use super::{Ros2Error, Ros2Options, ServiceMapping};
use futures::{FutureExt, StreamExt};
use rollbase_control::ports::{BaseState, CommandEvent, CommandKind};
use rollbase_control::runtime::CommandSender;
use ros2_client::dds::rustdds::DomainParticipantBuilder;
use ros2_client::dds::{Context, Node, Publisher};
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, QosProfile, ServiceTypeName};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// ROS 2's default QoS for topics and services: reliable, volatile, keep last 10.
pub fn ros_default_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

/// Counters of a running node (shared with its threads; read them any time).
#[derive(Debug, Default)]
pub struct NodeStats {
    /// Commands passed to the command port.
    pub commands_sent: AtomicU64,
    /// Commands dropped because the command queue was full.
    pub commands_dropped: AtomicU64,
    /// Commands refused by the node before the port (TwistStamped in a foreign frame).
    pub commands_refused: AtomicU64,
    /// Messages that could not be received (undecodable samples).
    pub receive_errors: AtomicU64,
    /// States taken from the state channel.
    pub states: AtomicU64,
    /// Messages published.
    pub published: AtomicU64,
    /// Publications that failed (e.g. a reliable reader not acknowledging in time).
    pub publish_errors: AtomicU64,
    /// Service requests answered.
    pub services_answered: AtomicU64,
}

impl NodeStats {
    fn add(c: &AtomicU64) {
        c.fetch_add(1, Ordering::Relaxed);
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

fn entity_err(
    what: &'static str,
    name: &str,
) -> impl FnOnce(ros2_client::CreateError) -> Ros2Error {
    let name = name.to_string();
    move |e| Ros2Error::Entity {
        what,
        name,
        message: format!("{e:?}"),
    }
}

fn split_type(def: &msg::MsgDef) -> (&str, &str) {
    let mut p = def.name.split('/');
    let pkg = p.next().unwrap_or_default();
    let ty = p.nth(1).unwrap_or_default();
    (pkg, ty)
}

/// The topic `T` is published or subscribed on, with ROS 2's default QoS.
fn ros_topic<T: RosMsg>(
    node: &mut Node,
    topic: &str,
) -> Result<(ros2_client::dds::rustdds::Topic, QosProfile), Ros2Error> {
    let (pkg, ty) = split_type(T::DEF);
    let qos = ros_default_qos();
    let name = Name::parse(topic).map_err(|e| Ros2Error::Entity {
        what: "topic",
        name: topic.into(),
        message: format!("{e:?}"),
    })?;
    let t = node
        .create_topic(&name, MessageTypeName::new(pkg, ty), &qos)
        .map_err(entity_err("topic", topic))?;
    Ok((t, qos))
}

/// A publisher of `T` on `topic` with ROS 2's default QoS (also for peers in tools and tests).
pub fn publisher<T: RosMsg + ros2_client::Message>(
    node: &mut Node,
    topic: &str,
) -> Result<Publisher<T>, Ros2Error> {
    let (t, qos) = ros_topic::<T>(node, topic)?;
    node.create_publisher::<T>(&t, Some(qos))
        .map_err(entity_err("publisher", topic))
}

/// A subscription to `T` on `topic` with ROS 2's default QoS (also for peers in tools and tests).
pub fn subscription<T: RosMsg + ros2_client::Message + 'static>(
    node: &mut Node,
    topic: &str,
) -> Result<ros2_client::dds::Subscription<T>, Ros2Error> {
    let (t, qos) = ros_topic::<T>(node, topic)?;
    node.create_subscription::<T>(&t, Some(qos))
        .map_err(entity_err("subscription", topic))
}

type TriggerServer = ros2_client::dds::Server<TriggerRequest, TriggerResponse>;

/// A service in the node's private namespace (`~/name`, i.e. `/<namespace>/<node>/name`).
fn trigger_server(
    node: &mut Node,
    name: &str,
    mapping: ServiceMapping,
) -> Result<TriggerServer, Ros2Error> {
    let fqn = node.fully_qualified_name();
    let n = Name::new(&fqn, name).map_err(|e| Ros2Error::Entity {
        what: "service",
        name: format!("{fqn}/{name}"),
        message: format!("{e:?}"),
    })?;
    let mapping = match mapping {
        ServiceMapping::Cyclone => ros2_client::ServiceMapping::Cyclone,
        ServiceMapping::Enhanced => ros2_client::ServiceMapping::Enhanced,
    };
    node.create_server::<TriggerRequest, TriggerResponse>(
        mapping,
        &n,
        &ServiceTypeName::new("std_srvs", "Trigger"),
        ros_default_qos(),
        ros_default_qos(),
    )
    .map_err(entity_err("service", &format!("{fqn}/{name}")))
}

/// The state the services report in their answers.
type SharedState = Arc<Mutex<Option<String>>>;

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
    let mut builder = DomainParticipantBuilder::new(domain);
    if !opts.only_addresses.is_empty() {
        builder = builder.with_only_networks(opts.only_addresses.iter().copied());
    }
    let participant = builder.build().map_err(|e| Ros2Error::Participant {
        domain,
        message: format!("{e:?}"),
    })?;
    let context =
        Context::from_domain_participant(participant).map_err(|e| Ros2Error::Participant {
            domain,
            message: format!("{e:?}"),
        })?;
    let node_name =
        NodeName::new(&opts.namespace, &opts.node_name).map_err(|e| Ros2Error::Option {
            option: "--ros2-namespace",
            message: format!("{}/{}: {e:?}", opts.namespace, opts.node_name),
        })?;
    let mut node = context
        .new_node(node_name, NodeOptions::new().enable_rosout(false))
        .map_err(|e| Ros2Error::Entity {
            what: "node",
            name: opts.node_name.clone(),
            message: format!("{e:?}"),
        })?;

    // Publishers.
    let odom_pub = publisher::<Odometry>(&mut node, &opts.topic("odom"))?;
    let tf_pub = if opts.publish_tf {
        Some(publisher::<TFMessage>(&mut node, &opts.topic("tf"))?)
    } else {
        None
    };
    let joints_pub = publisher::<JointState>(&mut node, &opts.topic("joint_states"))?;
    let diag_pub = publisher::<DiagnosticArray>(&mut node, &opts.topic("diagnostics"))?;
    let state_pub = publisher::<StringMsg>(&mut node, &opts.topic("supervisor_state"))?;

    // Commands.
    let cmd_vel = if opts.cmd_vel_stamped {
        CmdVelSub::Stamped(subscription::<TwistStamped>(
            &mut node,
            &opts.topic(&opts.cmd_vel_topic),
        )?)
    } else {
        CmdVelSub::Plain(subscription::<Twist>(
            &mut node,
            &opts.topic(&opts.cmd_vel_topic),
        )?)
    };
    let legs = subscription::<Float64MultiArray>(&mut node, &opts.topic(&opts.leg_topic))?;
    let stop_srv = trigger_server(&mut node, "stop", opts.service_mapping)?;
    let rearm_srv = trigger_server(&mut node, "rearm", opts.service_mapping)?;
    let spinner = node.spinner().map_err(entity_err("spinner", "node"))?;

    let stop = Arc::new(AtomicBool::new(false));
    let stats = Arc::new(NodeStats::default());
    let shared: SharedState = Arc::new(Mutex::new(None));
    let (wake_tx, wake_rx) = futures::channel::oneshot::channel::<()>();

    let cmd_side = CommandSide {
        cmd_tx,
        origin,
        stats: stats.clone(),
        shared: shared.clone(),
        base_frame: opts.frames.base.clone(),
        drops: DropLog::new(),
    };
    let cmd_thread = std::thread::Builder::new()
        .name("rollbase-ros2-cmd".into())
        .spawn(move || {
            futures::executor::block_on(
                cmd_side.run(node, spinner, cmd_vel, legs, stop_srv, rearm_srv, wake_rx),
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

enum CmdVelSub {
    Plain(ros2_client::dds::Subscription<Twist>),
    Stamped(ros2_client::dds::Subscription<TwistStamped>),
}

struct CommandSide {
    cmd_tx: CommandSender,
    origin: Instant,
    stats: Arc<NodeStats>,
    shared: SharedState,
    base_frame: String,
    drops: DropLog,
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

    #[allow(clippy::too_many_arguments)]
    async fn run(
        mut self,
        node: Node,
        spinner: ros2_client::dds::Spinner,
        cmd_vel: CmdVelSub,
        legs: ros2_client::dds::Subscription<Float64MultiArray>,
        stop_srv: TriggerServer,
        rearm_srv: TriggerServer,
        wake: futures::channel::oneshot::Receiver<()>,
    ) {
        let spin = spinner.spin().fuse();
        futures::pin_mut!(spin);
        let mut wake = wake.fuse();
        let legs_s = legs.async_stream();
        let stop_s = stop_srv.receive_request_stream();
        let rearm_s = rearm_srv.receive_request_stream();
        futures::pin_mut!(legs_s, stop_s, rearm_s);
        // One stream of velocity commands, whichever type.
        let mut vel_s = match &cmd_vel {
            CmdVelSub::Plain(s) => s
                .async_stream()
                .map(|r| r.map(|(m, _)| (None, m)).map_err(|e| format!("{e:?}")))
                .boxed_local(),
            CmdVelSub::Stamped(s) => s
                .async_stream()
                .map(|r| {
                    r.map(|(m, _)| (Some(m.header.frame_id), m.twist))
                        .map_err(|e| format!("{e:?}"))
                })
                .boxed_local(),
        }
        .fuse();
        let mut refused = DropLog::new();
        let mut recv_err = DropLog::new();
        loop {
            futures::select! {
                _ = wake => break,
                r = spin => {
                    if let Err(e) = r {
                        tracing::error!("ros2: the node's spinner stopped: {e:?}");
                    }
                }
                v = vel_s.next() => match v {
                    Some(Ok((frame, twist))) => {
                        match frame {
                            Some(f) if !f.is_empty() && f != self.base_frame => {
                                NodeStats::add(&self.stats.commands_refused);
                                refused.log(&format!(
                                    "velocity command in frame {f:?} ignored: rollbase takes body twists in {:?} (or an empty frame_id)",
                                    self.base_frame
                                ));
                            }
                            _ => {
                                self.send(convert::motion_command(&twist));
                            }
                        }
                    }
                    Some(Err(e)) => {
                        NodeStats::add(&self.stats.receive_errors);
                        recv_err.log(&format!("undecodable velocity command: {e}"));
                    }
                    None => break,
                },
                l = legs_s.next() => match l {
                    Some(Ok((m, _))) => {
                        self.send(convert::legs_command(&m.data));
                    }
                    Some(Err(e)) => {
                        NodeStats::add(&self.stats.receive_errors);
                        recv_err.log(&format!("undecodable leg command: {e:?}"));
                    }
                    None => break,
                },
                r = stop_s.next() => if let Some(Ok((id, _))) = r {
                    let queued = self.send(CommandKind::Stop);
                    let resp = self.answer("stop", queued);
                    if stop_srv.async_send_response(id, resp).await.is_ok() {
                        NodeStats::add(&self.stats.services_answered);
                    }
                },
                r = rearm_s.next() => if let Some(Ok((id, _))) = r {
                    let queued = self.send(CommandKind::Rearm);
                    let resp = self.answer("rearm", queued);
                    if rearm_srv.async_send_response(id, resp).await.is_ok() {
                        NodeStats::add(&self.stats.services_answered);
                    }
                },
            }
        }
        drop(vel_s);
        drop(cmd_vel);
        drop(node);
    }
}

struct PublishSide {
    opts: Ros2Options,
    stats: Arc<NodeStats>,
    shared: SharedState,
    odom_pub: Publisher<Odometry>,
    tf_pub: Option<Publisher<TFMessage>>,
    joints_pub: Publisher<JointState>,
    diag_pub: Publisher<DiagnosticArray>,
    state_pub: Publisher<StringMsg>,
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
                let r = self.odom_pub.publish(o);
                self.count(r.map_err(drop), &mut errors, "odom");
            }
            if let (Some(t), Some(p)) = (m.tf, &self.tf_pub) {
                let r = p.publish(t);
                self.count(r.map_err(drop), &mut errors, "tf");
            }
            if let Some(j) = m.joint_states {
                let r = self.joints_pub.publish(j);
                self.count(r.map_err(drop), &mut errors, "joint_states");
            }
            if let Some(d) = m.diagnostics {
                let r = self.diag_pub.publish(d);
                self.count(r.map_err(drop), &mut errors, "diagnostics");
            }
            if let Some(t) = m.supervisor_state {
                let r = self.state_pub.publish(t);
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
    const TEST_NAME: &str =
        "ros2::node::tests::node_talks_to_a_ros2_client_peer_in_a_private_netns";

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
    fn node_talks_to_a_ros2_client_peer_in_a_private_netns() {
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

        let ctx =
            Context::from_domain_participant(DomainParticipantBuilder::new(0).build().unwrap())
                .unwrap();
        let mut peer = ctx
            .new_node(
                NodeName::new("/", "peer").unwrap(),
                NodeOptions::new().enable_rosout(false),
            )
            .unwrap();
        let twist_pub = publisher::<Twist>(&mut peer, "/nstest/cmd_vel").unwrap();
        let odom_sub = subscription::<Odometry>(&mut peer, "/nstest/odom").unwrap();

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
            if let Ok(Some((o, _))) = odom_sub.take() {
                odom = Some(o);
            }
            // Once the peer sees the node, send commands until one is dropped.
            if odom.is_some() && sent < 50 && k.is_multiple_of(10) {
                let mut t = Twist::default();
                t.linear.x = 0.25 + sent as f64;
                if twist_pub.publish(t).is_ok() {
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
