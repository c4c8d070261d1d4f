//! `rollbase bridge`: a socketcand-compatible server hosting userspace CAN buses over TCP.
//!
//! Any number of clients connect (`rollbase run --bus socketcand://…`, `rollbase-sim --bus
//! socketcand://…`, python-can's `socketcand` interface, Kayak, a real socketcand client …),
//! open a channel by name and switch to raw mode; from then on every frame one client sends
//! goes to every *other* client that opened the same channel, stamped with the server's
//! receive time (like a CAN_RAW socket, a client does not get its own frames back). Each
//! channel name is its own bus, created when first opened. Protocol details (formats exactly
//! as socketcand writes and reads them) are in `rollbase_driver::bus::socketcand`.
//!
//! - Listens on 127.0.0.1:29536 by default (socketcand's port); `--listen ADDR:PORT` changes
//!   it, and anything but a loopback address is announced with a warning, because the
//!   protocol has no authentication: whoever reaches the port can put frames on the bus.
//! - Raw mode only. BCM-mode commands (`add`, `subscribe`, `filter` …) are answered with
//!   `< error … >`; `< send … >` is accepted in BCM mode as socketcand does; `< echo >` works
//!   everywhere.
//! - After the raw-mode `< ok >` the server waits [`BridgeConfig::raw_settle`] (100 ms), or
//!   until the client sends its next element, before forwarding frames to that client:
//!   python-can reads the `< ok >` with one `recv()` and compares it exactly, so a frame glued
//!   to it would fail its handshake. rollbase's client sends `< echo >` right after the
//!   handshake, so a controller gets the feedback of its very first SYNC.
//! - A client that does not read fast enough loses frames (counted and logged when it
//!   leaves), as a CAN socket whose receive queue overflows; it never slows the others.
//! - `--can IFACE` bridges the channel named IFACE to the SocketCAN interface IFACE in both
//!   directions. On a machine without kernel CAN this fails at start with the reason.

use clap::Args;
use rollbase_driver::bus::socketcan::AsyncSocketCanBus;
use rollbase_driver::bus::socketcand::{
    check_channel, format_frame_into, parse_element, Element, Framer, DEFAULT_PORT,
};
use rollbase_driver::bus::{AsyncCanBus, BusError};
use rollbase_driver::frame::TimestampedFrame;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::broadcast;

/// Arguments of `rollbase bridge`.
#[derive(Args, Debug)]
pub struct BridgeArgs {
    /// Address to listen on. Default loopback only; anything else is reachable by other
    /// machines and has no authentication. Port 0 picks a free port (printed at start).
    #[arg(long, default_value_t = SocketAddr::from(([127, 0, 0, 1], DEFAULT_PORT)))]
    listen: SocketAddr,
    /// Also bridge the channel named IFACE to the SocketCAN interface IFACE (needs kernel CAN).
    #[arg(long, value_name = "IFACE")]
    can: Option<String>,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
}

/// Why the bridge could not run.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    /// Binding the listening socket failed.
    #[error("cannot listen on {addr}: {source} (is another bridge or socketcand using the port? choose another with --listen 127.0.0.1:PORT, or port 0 for any free one)")]
    Listen {
        /// The address.
        addr: SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// The SocketCAN side could not be opened or failed.
    #[error("cannot bridge to SocketCAN interface {iface}: {source} (run without --can to serve a userspace-only bus)")]
    Can {
        /// Interface.
        iface: String,
        /// Why.
        source: BusError,
    },
    /// A bad option value.
    #[error("--{option} {value}: {reason}")]
    Option {
        /// The option.
        option: &'static str,
        /// Its value.
        value: String,
        /// What is wrong.
        reason: String,
    },
    /// The async runtime could not start.
    #[error("cannot start the network runtime: {0}")]
    Runtime(std::io::Error),
}

/// Tunables of the server.
#[derive(Debug, Clone, Copy)]
pub struct BridgeConfig {
    /// Delay between the raw-mode `< ok >` and the first forwarded frame.
    pub raw_settle: Duration,
    /// Frames buffered per channel for slow clients before they lose frames.
    pub queue: usize,
    /// Print one line per client event on stderr.
    pub verbose: bool,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        BridgeConfig {
            raw_settle: Duration::from_millis(100),
            queue: 4096,
            verbose: true,
        }
    }
}

/// A frame on a hub channel, with the id of the client that sent it.
#[derive(Debug, Clone, Copy)]
struct HubFrame {
    src: u64,
    tf: TimestampedFrame,
}

/// Source id of frames that came from the SocketCAN side.
const CAN_SRC: u64 = 0;

/// Totals over the server's life.
#[derive(Debug, Default)]
pub struct HubStats {
    /// Clients that connected.
    pub clients: AtomicU64,
    /// Frames clients (and the SocketCAN side) put on a bus.
    pub frames_in: AtomicU64,
    /// Frames delivered to clients.
    pub frames_out: AtomicU64,
    /// Frames slow clients lost.
    pub dropped: AtomicU64,
    /// Malformed or unsupported elements answered with `< error … >`.
    pub errors: AtomicU64,
}

/// The channels: one broadcast bus per name.
#[derive(Debug)]
pub struct Hub {
    cfg: BridgeConfig,
    buses: Mutex<HashMap<String, broadcast::Sender<HubFrame>>>,
    next_id: AtomicU64,
    /// Totals.
    pub stats: HubStats,
}

impl Hub {
    /// An empty hub.
    pub fn new(cfg: BridgeConfig) -> Arc<Hub> {
        Arc::new(Hub {
            cfg,
            buses: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(CAN_SRC + 1),
            stats: HubStats::default(),
        })
    }

    fn bus(&self, name: &str) -> broadcast::Sender<HubFrame> {
        let mut m = self
            .buses
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        m.entry(name.to_string())
            .or_insert_with(|| broadcast::channel(self.cfg.queue.max(1)).0)
            .clone()
    }
}

fn unix_now() -> Duration {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
}

/// Error text without the protocol's delimiters.
fn error_element(text: &str) -> String {
    let clean: String = text
        .chars()
        .map(|c| if c == '<' || c == '>' { '\'' } else { c })
        .collect();
    format!("< error {clean} >")
}

enum Mode {
    NoBus,
    Bcm,
    Raw,
}

/// Serves one client until it disconnects.
async fn serve_client(stream: TcpStream, peer: SocketAddr, hub: Arc<Hub>) {
    let id = hub.next_id.fetch_add(1, Ordering::Relaxed);
    hub.stats.clients.fetch_add(1, Ordering::Relaxed);
    let verbose = hub.cfg.verbose;
    if verbose {
        eprintln!("bridge: client {id} ({peer}) connected");
    }
    let _ = stream.set_nodelay(true);
    let (mut rd, mut wr) = stream.into_split();
    let (mut sent, mut delivered, mut dropped) = (0u64, 0u64, 0u64);
    let outcome: Result<(), String> = async {
        wr.write_all(b"< hi >").await.map_err(|e| e.to_string())?;
        let mut framer = Framer::new();
        let mut mode = Mode::NoBus;
        let mut channel = String::new();
        let mut tx: Option<broadcast::Sender<HubFrame>> = None;
        let mut rx: Option<broadcast::Receiver<HubFrame>> = None;
        let mut subscribe_at: Option<tokio::time::Instant> = None;
        let mut buf = vec![0u8; 8192];
        let mut out = String::with_capacity(8192);
        loop {
            // Handle every complete element first.
            loop {
                let parsed = match framer.next_element() {
                    None => break,
                    Some(r) => r.and_then(parse_element),
                };
                // Any element after the raw-mode `< ok >` shows the client has read the
                // reply: start forwarding frames now instead of after the settle time
                // (rollbase's own client sends `< echo >` for this right after the handshake).
                // Subscribe before the element is handled: a frame it sends must not get a
                // reply (an SDO response, a boot-up) that this client misses.
                if matches!(mode, Mode::Raw)
                    && subscribe_at.is_some()
                    && !matches!(parsed, Ok(Element::RawMode))
                {
                    subscribe_at = None;
                    rx = tx.as_ref().map(|t| t.subscribe());
                    if verbose {
                        eprintln!("bridge: client {id} in raw mode on {channel}");
                    }
                }
                let reply: Option<String> = match (parsed, &mode) {
                    (Ok(Element::Echo), _) => Some("< echo >".into()),
                    (Ok(Element::Open(ch)), Mode::NoBus) => {
                        if verbose {
                            eprintln!("bridge: client {id} opened channel {ch}");
                        }
                        tx = Some(hub.bus(&ch));
                        channel = ch;
                        mode = Mode::Bcm;
                        Some("< ok >".into())
                    }
                    (Ok(Element::Open(_)), _) => {
                        Some(error_element("a channel is already open on this connection"))
                    }
                    (Ok(Element::RawMode), Mode::Bcm | Mode::Raw) => {
                        if !matches!(mode, Mode::Raw) {
                            mode = Mode::Raw;
                            subscribe_at =
                                Some(tokio::time::Instant::now() + hub.cfg.raw_settle);
                        }
                        Some("< ok >".into())
                    }
                    (Ok(Element::BcmMode), Mode::Bcm) => Some("< ok >".into()),
                    (Ok(Element::BcmMode), Mode::Raw) => Some(error_element(
                        "bcm mode is not supported by rollbase bridge; use rawmode",
                    )),
                    (Ok(Element::Send(frame)), Mode::Bcm | Mode::Raw) => {
                        if let Some(t) = &tx {
                            let _ = t.send(HubFrame {
                                src: id,
                                tf: TimestampedFrame {
                                    timestamp: unix_now(),
                                    frame,
                                },
                            });
                        }
                        sent += 1;
                        hub.stats.frames_in.fetch_add(1, Ordering::Relaxed);
                        None
                    }
                    (Ok(Element::Unsupported(w)), _) => Some(error_element(&format!(
                        "{w}: 29-bit, RTR and CAN FD frames are not carried by rollbase bridge"
                    ))),
                    (Ok(Element::Hi | Element::Ok | Element::Frame(_) | Element::Error(_)), _) => {
                        Some(error_element("unexpected server element from a client"))
                    }
                    (Ok(Element::Other(cmd)), _) if cmd.is_empty() => {
                        Some(error_element("empty command"))
                    }
                    (Ok(Element::Other(cmd)), _) => Some(error_element(&format!(
                        "unknown or unsupported command {:?} (rollbase bridge speaks raw mode: open, rawmode, send, echo)",
                        cmd.split_whitespace().next().unwrap_or("")
                    ))),
                    (Ok(_), Mode::NoBus) => {
                        Some(error_element("open a channel first: < open vcan0 >"))
                    }
                    (Err(e), _) => Some(error_element(&e.to_string())),
                };
                if let Some(r) = reply {
                    if r.starts_with("< error") {
                        hub.stats.errors.fetch_add(1, Ordering::Relaxed);
                    }
                    wr.write_all(r.as_bytes())
                        .await
                        .map_err(|e| e.to_string())?;
                }
            }
            let settle = subscribe_at;
            tokio::select! {
                r = rd.read(&mut buf) => {
                    match r {
                        Ok(0) => return Ok(()),
                        Ok(n) => framer.extend(&buf[..n]),
                        Err(e) => return Err(e.to_string()),
                    }
                }
                _ = async { if let Some(t) = settle { tokio::time::sleep_until(t).await } }, if settle.is_some() => {
                    subscribe_at = None;
                    rx = tx.as_ref().map(|t| t.subscribe());
                    if verbose {
                        eprintln!("bridge: client {id} in raw mode on {channel}");
                    }
                }
                r = async { match rx.as_mut() { Some(r) => r.recv().await, None => std::future::pending().await } }, if rx.is_some() => {
                    out.clear();
                    let mut push = |r: Result<HubFrame, broadcast::error::RecvError>, out: &mut String| -> bool {
                        match r {
                            Ok(f) if f.src != id => {
                                format_frame_into(out, &f.tf);
                                delivered += 1;
                                true
                            }
                            Ok(_) => true,
                            Err(broadcast::error::RecvError::Lagged(n)) => {
                                dropped += n;
                                hub.stats.dropped.fetch_add(n, Ordering::Relaxed);
                                true
                            }
                            Err(broadcast::error::RecvError::Closed) => false,
                        }
                    };
                    if !push(r, &mut out) {
                        return Err("channel closed".into());
                    }
                    // Batch what is already queued into one write.
                    if let Some(r) = rx.as_mut() {
                        for _ in 0..128 {
                            match r.try_recv() {
                                Ok(f) => { push(Ok(f), &mut out); }
                                Err(broadcast::error::TryRecvError::Lagged(n)) => {
                                    push(Err(broadcast::error::RecvError::Lagged(n)), &mut out);
                                }
                                Err(_) => break,
                            }
                        }
                    }
                    if !out.is_empty() {
                        wr.write_all(out.as_bytes()).await.map_err(|e| e.to_string())?;
                    }
                }
            }
        }
    }
    .await;
    hub.stats.frames_out.fetch_add(delivered, Ordering::Relaxed);
    if verbose {
        let why = match outcome {
            Ok(()) => String::new(),
            Err(e) => format!(" ({e})"),
        };
        eprintln!(
            "bridge: client {id} left{why}: {sent} frames sent to the bus, {delivered} delivered to it, {dropped} lost because it read too slowly"
        );
    }
}

/// Moves frames between the hub channel `iface` and the SocketCAN interface of that name.
async fn bridge_can(mut can: AsyncSocketCanBus, hub: Arc<Hub>) -> BridgeError {
    let iface = can.name().to_string();
    let tx = hub.bus(&iface);
    let mut rx = tx.subscribe();
    loop {
        tokio::select! {
            r = can.recv() => match r {
                Ok(tf) => {
                    hub.stats.frames_in.fetch_add(1, Ordering::Relaxed);
                    let _ = tx.send(HubFrame { src: CAN_SRC, tf });
                }
                Err(e) if e.is_retryable() => {}
                Err(source) => return BridgeError::Can { iface, source },
            },
            r = rx.recv() => match r {
                Ok(f) if f.src != CAN_SRC => {
                    if let Err(e) = AsyncCanBus::send(&mut can, &f.tf.frame).await {
                        if !e.is_retryable() {
                            return BridgeError::Can { iface, source: e };
                        }
                    }
                }
                Ok(_) => {}
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    hub.stats.dropped.fetch_add(n, Ordering::Relaxed);
                }
                Err(broadcast::error::RecvError::Closed) => {
                    return BridgeError::Can {
                        iface: iface.clone(),
                        source: BusError::Closed { iface },
                    }
                }
            },
        }
    }
}

/// Accepts clients on `listener` until `shutdown` completes (or the SocketCAN side fails).
pub async fn serve(
    listener: TcpListener,
    hub: Arc<Hub>,
    can: Option<AsyncSocketCanBus>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), BridgeError> {
    let can_task = can.map(|c| tokio::spawn(bridge_can(c, hub.clone())));
    let can_failed = async {
        match can_task {
            Some(t) => match t.await {
                Ok(e) => e,
                Err(_) => {
                    BridgeError::Runtime(std::io::Error::other("the SocketCAN task panicked"))
                }
            },
            None => std::future::pending().await,
        }
    };
    tokio::pin!(shutdown);
    tokio::pin!(can_failed);
    loop {
        tokio::select! {
            _ = &mut shutdown => return Ok(()),
            e = &mut can_failed => return Err(e),
            r = listener.accept() => match r {
                Ok((s, peer)) => { tokio::spawn(serve_client(s, peer, hub.clone())); }
                Err(e) => {
                    // EMFILE and friends: say so, back off briefly, keep serving.
                    eprintln!("bridge: accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
        }
    }
}

/// `rollbase bridge`: runs the server until Ctrl-C or `--duration`; returns the exit code.
pub fn run(a: BridgeArgs) -> Result<i32, BridgeError> {
    let duration = match a.duration {
        None => None,
        Some(s) if s.is_finite() && s > 0.0 && s < 1e9 => Some(Duration::from_secs_f64(s)),
        Some(s) => {
            return Err(BridgeError::Option {
                option: "duration",
                value: s.to_string(),
                reason: "must be a positive number of seconds".into(),
            })
        }
    };
    if let Some(iface) = &a.can {
        check_channel(iface).map_err(|r| BridgeError::Option {
            option: "can",
            value: iface.clone(),
            reason: r.into(),
        })?;
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(BridgeError::Runtime)?;
    rt.block_on(async {
        // The SocketCAN side first: a machine without kernel CAN fails here, before anyone
        // connects to a bridge that would not bridge.
        let can = match &a.can {
            Some(iface) => Some(AsyncSocketCanBus::open(iface).map_err(|source| {
                BridgeError::Can {
                    iface: iface.clone(),
                    source,
                }
            })?),
            None => None,
        };
        let listener = TcpListener::bind(a.listen)
            .await
            .map_err(|source| BridgeError::Listen {
                addr: a.listen,
                source,
            })?;
        let local = listener.local_addr().unwrap_or(a.listen);
        if !local.ip().is_loopback() {
            eprintln!("bridge: WARNING: listening on {local}, which is NOT a loopback address.");
            eprintln!("bridge: WARNING: anyone who can reach this port can send frames onto the bus (socketcand has no authentication).");
            eprintln!("bridge: WARNING: on a robot these frames move motors; use 127.0.0.1 unless you mean it.");
        }
        eprintln!(
            "bridge: listening on {local} (socketcand raw mode{}); clients: --bus socketcand://{local}/vcan0",
            match &a.can {
                Some(i) => format!(", channel {i} bridged to SocketCAN {i}"),
                None => String::new(),
            }
        );
        let hub = Hub::new(BridgeConfig::default());
        let shutdown = async {
            let timer = async {
                match duration {
                    Some(d) => tokio::time::sleep(d).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                r = tokio::signal::ctrl_c() => {
                    if let Err(e) = r {
                        eprintln!("bridge: cannot listen for Ctrl-C ({e}); stopping");
                    }
                }
                _ = timer => {}
            }
        };
        let r = serve(listener, hub.clone(), can, shutdown).await;
        let s = &hub.stats;
        eprintln!(
            "bridge: stopped: {} clients served, {} frames onto the bus, {} delivered, {} lost by slow clients, {} error replies",
            s.clients.load(Ordering::Relaxed),
            s.frames_in.load(Ordering::Relaxed),
            s.frames_out.load(Ordering::Relaxed),
            s.dropped.load(Ordering::Relaxed),
            s.errors.load(Ordering::Relaxed),
        );
        r.map(|()| 0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rollbase_driver::bus::socketcand::SocketcandBus;
    use rollbase_driver::bus::CanBus;
    use rollbase_driver::frame::CanFrame;
    use std::io::{Read, Write};
    use std::time::Instant;

    /// A server on a free loopback port in its own thread; dropping the guard stops it.
    struct Server {
        port: u16,
        stop: Option<tokio::sync::oneshot::Sender<()>>,
        thread: Option<std::thread::JoinHandle<Arc<Hub>>>,
    }

    impl Server {
        fn start() -> Server {
            Server::start_with(Duration::ZERO)
        }

        fn start_with(raw_settle: Duration) -> Server {
            let (port_tx, port_rx) = std::sync::mpsc::channel();
            let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
            let thread = std::thread::spawn(move || {
                let rt = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .expect("runtime");
                let hub = Hub::new(BridgeConfig {
                    raw_settle,
                    queue: 1024,
                    verbose: false,
                });
                rt.block_on(async {
                    let l = TcpListener::bind("127.0.0.1:0").await.expect("bind");
                    port_tx
                        .send(l.local_addr().expect("addr").port())
                        .expect("port");
                    serve(l, hub.clone(), None, async {
                        let _ = stop_rx.await;
                    })
                    .await
                    .expect("serve");
                });
                hub
            });
            let port = port_rx
                .recv_timeout(Duration::from_secs(5))
                .expect("server port");
            Server {
                port,
                stop: Some(stop_tx),
                thread: Some(thread),
            }
        }

        fn url(&self, ch: &str) -> String {
            format!("socketcand://127.0.0.1:{}/{ch}", self.port)
        }

        fn stop(mut self) -> Arc<Hub> {
            if let Some(s) = self.stop.take() {
                let _ = s.send(());
            }
            self.thread
                .take()
                .expect("thread")
                .join()
                .expect("server thread")
        }
    }

    impl Drop for Server {
        fn drop(&mut self) {
            if let Some(s) = self.stop.take() {
                let _ = s.send(());
            }
        }
    }

    fn recv(bus: &mut SocketcandBus) -> Option<TimestampedFrame> {
        bus.recv_until(Instant::now() + Duration::from_secs(5))
            .expect("recv")
    }

    /// Opens a client and waits until the server has subscribed it (a probe frame from a
    /// helper client arrives).
    fn joined(server: &Server, ch: &str) -> SocketcandBus {
        let mut bus = SocketcandBus::open(&server.url(ch)).expect("open");
        let mut probe = SocketcandBus::open(&server.url(ch)).expect("probe");
        let p = CanFrame::new(0x7FF, &[0xEE]).expect("frame");
        for _ in 0..500 {
            CanBus::send(&mut probe, &p).expect("probe send");
            if let Ok(Some(f)) = bus.recv_until(Instant::now() + Duration::from_millis(10)) {
                if f.frame == p {
                    // Drain further probes.
                    while let Ok(Some(_)) =
                        bus.recv_until(Instant::now() + Duration::from_millis(20))
                    {
                    }
                    return bus;
                }
            }
        }
        panic!("client never joined channel {ch}");
    }

    #[test]
    fn frames_reach_every_other_client_on_the_channel_only() {
        let server = Server::start();
        let mut a = joined(&server, "vcan0");
        let mut b = joined(&server, "vcan0");
        let mut other = joined(&server, "vcan1");
        // Probe frames of later joins reached the earlier clients: drop them.
        for bus in [&mut a, &mut b, &mut other] {
            while let Ok(Some(_)) = bus.recv_until(Instant::now() + Duration::from_millis(50)) {}
        }
        let t0 = unix_now();
        let f1 = CanFrame::new(0x080, &[1, 0, 0x0A, 0xC5]).expect("frame");
        CanBus::send(&mut a, &f1).expect("send");
        let got = recv(&mut b).expect("b gets a's frame");
        assert_eq!(got.frame, f1);
        assert!(
            got.timestamp >= t0 - Duration::from_millis(1),
            "server time stamp"
        );
        let f2 = CanFrame::new(0x181, &[0, 1, 2, 3, 4, 5, 6, 7]).expect("frame");
        CanBus::send(&mut b, &f2).expect("send");
        // a gets b's frame and not its own f1.
        assert_eq!(recv(&mut a).expect("a gets b's frame").frame, f2);
        assert_eq!(
            a.recv_until(Instant::now() + Duration::from_millis(100))
                .expect("recv"),
            None,
            "no echo of own frames"
        );
        assert_eq!(
            other
                .recv_until(Instant::now() + Duration::from_millis(100))
                .expect("recv"),
            None,
            "channel vcan1 is a different bus"
        );
        // Many frames in a burst arrive in order.
        for i in 0..200u16 {
            let f = CanFrame::new(0x200 + (i % 16), &i.to_le_bytes()).expect("frame");
            CanBus::send(&mut a, &f).expect("send");
        }
        for i in 0..200u16 {
            let f = recv(&mut b).expect("burst frame");
            assert_eq!(f.frame.data(), &i.to_le_bytes(), "frame {i}");
        }
        drop((a, b, other));
        let hub = server.stop();
        assert!(hub.stats.frames_in.load(Ordering::Relaxed) >= 202);
        assert_eq!(hub.stats.dropped.load(Ordering::Relaxed), 0);
    }

    fn read_reply(s: &mut std::net::TcpStream) -> String {
        let mut buf = [0u8; 256];
        let n = s.read(&mut buf).expect("read");
        String::from_utf8_lossy(&buf[..n]).into_owned()
    }

    #[test]
    fn handshake_replies_are_single_exact_writes_and_python_can_sends_parse() {
        let server = Server::start();
        let mut listener = joined(&server, "vcan0");
        let mut s = std::net::TcpStream::connect(("127.0.0.1", server.port)).expect("connect");
        s.set_read_timeout(Some(Duration::from_secs(5)))
            .expect("timeout");
        // Exactly python-can's SocketCanDaemonBus handshake: recv() must equal the reply.
        assert_eq!(read_reply(&mut s), "< hi >");
        s.write_all(b"< open vcan0 >").expect("open");
        assert_eq!(read_reply(&mut s), "< ok >");
        s.write_all(b"< rawmode >").expect("raw");
        assert_eq!(read_reply(&mut s), "< ok >");
        // python-can's send spelling (unpadded lower-case bytes, hex DLC).
        s.write_all(b"< send 201 6 0 11 22 33 44 ab >")
            .expect("send");
        let f = recv(&mut listener).expect("frame");
        assert_eq!(f.frame.id(), 0x201);
        assert_eq!(f.frame.data(), &[0, 0x11, 0x22, 0x33, 0x44, 0xAB]);
        // Errors are replies, the connection stays usable.
        s.write_all(b"< send 201 3 1 >").expect("bad send");
        let r = read_reply(&mut s);
        assert!(
            r.starts_with("< error ") && r.contains("DLC 3 but 1"),
            "{r}"
        );
        s.write_all(b"< subscribe 0 0 123 >").expect("bcm");
        let r = read_reply(&mut s);
        assert!(r.contains("unsupported command \"subscribe\""), "{r}");
        s.write_all(b"< send 1AAAAAAA 2 1 F1 >").expect("eff");
        assert!(read_reply(&mut s).contains("29-bit"));
        s.write_all(b"< echo >").expect("echo");
        assert_eq!(read_reply(&mut s), "< echo >");
        // Frames from others arrive exactly in socketcand's format.
        let f = CanFrame::new(0x181, &[0, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77]).expect("f");
        CanBus::send(&mut listener, &f).expect("send");
        let r = read_reply(&mut s);
        let (head, tail) = r.split_at(r.find(' ').map(|i| i + 1).unwrap_or(0));
        assert_eq!(head, "< ");
        let parts: Vec<&str> = tail.split(' ').collect();
        assert_eq!(parts[0], "frame");
        assert_eq!(parts[1], "181");
        let ts = parts[2];
        let (sec, usec) = ts.split_once('.').expect("SEC.USEC");
        assert!(sec.len() >= 10 && usec.len() == 6, "{ts}");
        assert_eq!(&parts[3..], ["0011223344556677", ">"]);
    }

    #[test]
    fn a_reply_to_the_first_frame_after_the_handshake_reaches_its_sender() {
        // A settle time far longer than the test: only the early subscription on the
        // client's first element can deliver the reply.
        let server = Server::start_with(Duration::from_secs(30));
        let mut device = joined(&server, "vcan0");
        let mut s = std::net::TcpStream::connect(("127.0.0.1", server.port)).expect("connect");
        s.set_read_timeout(Some(Duration::from_secs(5)))
            .expect("timeout");
        assert_eq!(read_reply(&mut s), "< hi >");
        s.write_all(b"< open vcan0 >").expect("open");
        assert_eq!(read_reply(&mut s), "< ok >");
        s.write_all(b"< rawmode >").expect("raw");
        assert_eq!(read_reply(&mut s), "< ok >");
        // An SDO upload request, answered by the device as soon as it sees it.
        s.write_all(b"< send 601 8 40 00 10 00 00 00 00 00 >")
            .expect("send");
        let req = recv(&mut device).expect("request reaches the device");
        assert_eq!(req.frame.id(), 0x601);
        let resp = CanFrame::new(0x581, &[0x43, 0, 0x10, 0, 0x92, 0x01, 0x02, 0]).expect("f");
        CanBus::send(&mut device, &resp).expect("reply");
        let r = read_reply(&mut s);
        assert!(
            r.contains("frame 581 ") && r.contains("4300100092010200"),
            "{r}"
        );
    }

    #[test]
    fn operations_before_open_are_refused() {
        let server = Server::start();
        let mut s = std::net::TcpStream::connect(("127.0.0.1", server.port)).expect("connect");
        s.set_read_timeout(Some(Duration::from_secs(5)))
            .expect("timeout");
        assert_eq!(read_reply(&mut s), "< hi >");
        s.write_all(b"< rawmode >").expect("raw");
        assert!(read_reply(&mut s).contains("open a channel first"));
        s.write_all(b"< open a_name_longer_than_16 >")
            .expect("open");
        assert!(read_reply(&mut s).contains("at most 16"));
    }

    #[test]
    fn bridging_to_a_missing_socketcan_interface_fails_clearly() {
        let e = run(BridgeArgs {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            can: Some("rbnosuch9".into()),
            duration: Some(0.1),
        })
        .expect_err("no such interface / no kernel CAN");
        let msg = e.to_string();
        assert!(
            msg.contains("cannot bridge to SocketCAN interface rbnosuch9")
                && msg.contains("without --can"),
            "{msg}"
        );
        assert!(
            msg.contains("no CAN support") || msg.contains("does not exist"),
            "{msg}"
        );
    }
}
