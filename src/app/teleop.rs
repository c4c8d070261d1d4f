//! `rollbase demo --teleop`: the keyboard as a command source, with a live status line.
//!
//! Keys (the terminal is put in raw mode, and restored on exit):
//!
//! | key | command |
//! |---|---|
//! | ↑ / W, ↓ / S | forward / backward (0.3 m/s) |
//! | ← / A, → / D | left / right (0.3 m/s) |
//! | Q / E | rotate left / right (0.5 rad/s) |
//! | + / - | all legs out / in by 2 cm |
//! | space | controlled stop (latched: R re-arms) |
//! | R | re-arm |
//! | Esc, Ctrl-C | controlled stop, then quit |
//!
//! A terminal sends a held key again and again (after an initial delay of about half a
//! second), never its release: a key keeps its motion for [`HOLD`] after it was last seen, and
//! the command is repeated at 20 Hz meanwhile; then a zero twist follows (the platform stops
//! within its limits, steering held). Should the keyboard thread stall, the driver's own
//! command timeout stops the platform.
//!
//! The terminal's mode is restored however the run ends (Esc, Ctrl-C, SIGTERM, an error): by
//! the keyboard thread when it ends, and at process exit otherwise (the thread may still be
//! blocked reading the keyboard then). Log lines and the status line share the terminal: a
//! log line clears the status line first ([`log_writer`]), the status line is drawn again
//! below it, and the last status line is ended with a newline before the run's report.

use rollbase_control::runtime::CommandSender;
use rollbase_control::service::ports::{
    BaseState, CommandEvent, CommandKind, LegTargets, MotionCommand,
};
use rollbase_control::types::Twist;
use rollbase_control::Platform;
use std::io::{IsTerminal, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::common::CliError;
use super::common::{Ready, StateConsumer};

/// How long a key's motion lasts after the key was last seen (s): longer than a terminal's
/// auto-repeat delay, so a held key moves smoothly.
pub(crate) const HOLD: Duration = Duration::from_millis(600);
/// Linear speed of the arrow keys (m/s).
const SPEED: f64 = 0.3;
/// Rotation speed of Q/E (rad/s).
const TURN: f64 = 0.5;
/// Leg step of +/- (m).
const LEG_STEP: f64 = 0.02;

/// One key's meaning.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Key {
    /// Move with this twist while held.
    Move(Twist),
    /// Legs out (+1) or in (−1).
    Legs(f64),
    /// Controlled stop.
    Stop,
    /// Re-arm.
    Rearm,
    /// Stop and quit.
    Quit,
}

/// Decodes the keys in `bytes` (raw terminal input; arrow keys arrive as ESC [ A … D).
pub(crate) fn decode(bytes: &[u8]) -> Vec<Key> {
    let mut out = Vec::new();
    let mut i = 0;
    let tw = |vx, vy, omega| Key::Move(Twist { vx, vy, omega });
    while i < bytes.len() {
        let b = bytes[i];
        if b == 0x1B {
            if bytes.get(i + 1) == Some(&b'[') {
                if let Some(c) = bytes.get(i + 2) {
                    match c {
                        b'A' => out.push(tw(SPEED, 0.0, 0.0)),
                        b'B' => out.push(tw(-SPEED, 0.0, 0.0)),
                        b'C' => out.push(tw(0.0, -SPEED, 0.0)),
                        b'D' => out.push(tw(0.0, SPEED, 0.0)),
                        _ => {}
                    }
                    i += 3;
                    continue;
                }
            }
            out.push(Key::Quit);
            i += 1;
            continue;
        }
        match b.to_ascii_lowercase() {
            b'w' => out.push(tw(SPEED, 0.0, 0.0)),
            b's' => out.push(tw(-SPEED, 0.0, 0.0)),
            b'a' => out.push(tw(0.0, SPEED, 0.0)),
            b'd' => out.push(tw(0.0, -SPEED, 0.0)),
            b'q' => out.push(tw(0.0, 0.0, TURN)),
            b'e' => out.push(tw(0.0, 0.0, -TURN)),
            b'+' | b'=' => out.push(Key::Legs(1.0)),
            b'-' | b'_' => out.push(Key::Legs(-1.0)),
            b' ' => out.push(Key::Stop),
            b'r' => out.push(Key::Rearm),
            _ => {}
        }
        i += 1;
    }
    out
}

/// The terminal's mode before raw mode, while raw mode is on (for [`restore_terminal`]).
static SAVED_MODE: Mutex<Option<libc::termios>> = Mutex::new(None);

/// Puts the terminal back in the mode it had before raw mode (once; later calls do nothing).
fn restore_terminal() {
    // At exit another thread may hold the lock forever (it cannot: it only holds it here),
    // so never wait for it.
    let Ok(mut saved) = SAVED_MODE.try_lock() else {
        return;
    };
    if let Some(t) = saved.take() {
        // SAFETY: restores a mode tcgetattr filled in for fd 0.
        unsafe {
            libc::tcsetattr(0, libc::TCSANOW, &t);
        }
    }
}

extern "C" fn restore_terminal_at_exit() {
    restore_terminal();
}

/// The terminal in raw mode (no line buffering, no echo; Ctrl-C still signals), restored when
/// dropped or, if it never is (its thread blocked in a read at exit), when the process exits.
struct RawTerminal;

impl RawTerminal {
    fn enter() -> Result<Self, CliError> {
        if !std::io::stdin().is_terminal() {
            return Err(CliError::Usage(
                "--teleop reads the keyboard: run it in a terminal (stdin is not one)".into(),
            ));
        }
        // SAFETY: tcgetattr/tcsetattr on fd 0 with a termios value it fills in.
        unsafe {
            let mut t: libc::termios = std::mem::zeroed();
            if libc::tcgetattr(0, &mut t) != 0 {
                return Err(CliError::Usage(format!(
                    "cannot read the terminal's mode: {}",
                    std::io::Error::last_os_error()
                )));
            }
            let saved = t;
            t.c_lflag &= !(libc::ICANON | libc::ECHO);
            t.c_cc[libc::VMIN] = 1;
            t.c_cc[libc::VTIME] = 0;
            if let Ok(mut s) = SAVED_MODE.lock() {
                *s = Some(saved);
            }
            // std::process::exit (how every run ends) runs the C atexit handlers.
            libc::atexit(restore_terminal_at_exit);
            if libc::tcsetattr(0, libc::TCSANOW, &t) != 0 {
                return Err(CliError::Usage(format!(
                    "cannot put the terminal in raw mode: {}",
                    std::io::Error::last_os_error()
                )));
            }
            Ok(Self)
        }
    }
}

impl Drop for RawTerminal {
    fn drop(&mut self) {
        restore_terminal();
    }
}

/// Whether the status line is on the terminal (log lines clear it first).
static STATUS_SHOWN: AtomicBool = AtomicBool::new(false);

/// The log's writer (stderr; `init_logging` installs it): while the teleop status line is on
/// the terminal, each log line first clears it, so the log line starts at the left margin
/// instead of after the status text (the status line is drawn again below on its next
/// update).
pub(crate) fn log_writer() -> LogWriter {
    LogWriter { first: true }
}

/// One log line's writer ([`log_writer`]).
pub(crate) struct LogWriter {
    first: bool,
}

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let mut e = std::io::stderr().lock();
        if std::mem::take(&mut self.first) && STATUS_SHOWN.load(Ordering::Relaxed) {
            e.write_all(b"\r\x1b[2K")?;
        }
        e.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// The keyboard state between the reader and the 20 Hz sender.
#[derive(Default)]
struct Keys {
    motion: Option<(Twist, Instant)>,
    legs: f64,
    pending: Vec<CommandKind>,
    quit: bool,
}

/// Starts the keyboard reader and the 20 Hz command sender.
pub(crate) fn start(
    tx: CommandSender,
    ready: Arc<Ready>,
    stop: Arc<AtomicBool>,
    p: &Platform,
) -> Result<(), CliError> {
    let raw = RawTerminal::enter()?;
    errln!(
        "teleop: arrows/WASD move, Q/E rotate, +/- legs, space stops, R re-arms, Esc or Ctrl-C quits"
    );
    let keys = Arc::new(Mutex::new(Keys {
        legs: p
            .wheels
            .iter()
            .map(|w| w.lambda_nominal)
            .fold(0.0, f64::max),
        ..Default::default()
    }));
    let (lmin, lmax) = p.wheels.iter().fold((0.0f64, 1.0f64), |(lo, hi), w| {
        (lo.max(w.lambda_min), hi.min(w.lambda_max))
    });
    let n = p.n();
    {
        let keys = keys.clone();
        let stop = stop.clone();
        std::thread::Builder::new()
            .name("rollbase-keyboard".into())
            .spawn(move || {
                let _raw = raw;
                let mut buf = [0u8; 16];
                let mut stdin = std::io::stdin();
                while !stop.load(Ordering::SeqCst) {
                    let k = match stdin.read(&mut buf) {
                        Ok(0) | Err(_) => break,
                        Ok(k) => k,
                    };
                    let Ok(mut s) = keys.lock() else { break };
                    for key in decode(&buf[..k]) {
                        match key {
                            Key::Move(t) => s.motion = Some((t, Instant::now())),
                            Key::Legs(d) => {
                                s.legs = (s.legs + d * LEG_STEP).clamp(lmin, lmax);
                                let l = s.legs;
                                s.pending
                                    .push(CommandKind::Legs(LegTargets::from_slice(&vec![l; n])));
                            }
                            Key::Stop => {
                                s.motion = None;
                                s.pending.push(CommandKind::Stop);
                            }
                            Key::Rearm => s.pending.push(CommandKind::Rearm),
                            Key::Quit => s.quit = true,
                        }
                    }
                    if s.quit {
                        break;
                    }
                }
            })
            .map_err(|e| CliError::Usage(format!("cannot start the keyboard reader: {e}")))?;
    }
    std::thread::Builder::new()
        .name("rollbase-teleop".into())
        .spawn(move || {
            if ready.wait(&stop).is_none() {
                return;
            }
            loop {
                let mut send = Vec::new();
                {
                    let Ok(mut s) = keys.lock() else { return };
                    if s.quit {
                        send.push(CommandKind::Shutdown);
                    }
                    send.append(&mut s.pending);
                    let twist = match s.motion {
                        Some((t, at)) if at.elapsed() < HOLD => t,
                        _ => Twist::default(),
                    };
                    send.push(CommandKind::Motion(MotionCommand { twist, legs: None }));
                }
                for kind in send {
                    let quit = matches!(kind, CommandKind::Shutdown);
                    if tx.try_send(CommandEvent { t: 0.0, kind }).is_err() && quit {
                        stop.store(true, Ordering::SeqCst);
                    }
                    if quit {
                        stop.store(true, Ordering::SeqCst);
                        return;
                    }
                }
                if stop.load(Ordering::SeqCst) {
                    return;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        })
        .map_err(|e| CliError::Usage(format!("cannot start the teleop sender: {e}")))?;
    Ok(())
}

/// Ends the status line (a newline) when the state consumer is dropped, at the end of the
/// run, so the report that follows starts on a line of its own.
struct StatusLine;

impl Drop for StatusLine {
    fn drop(&mut self) {
        if STATUS_SHOWN.swap(false, Ordering::Relaxed) {
            errln!();
        }
    }
}

/// The live status line of teleop (stderr, about 5 times a second): pose, speeds, state and
/// what limits the motion.
pub(crate) fn status_line() -> StateConsumer {
    let mut last = Instant::now();
    let line = StatusLine;
    Box::new(move |s: &BaseState| {
        let _ = &line;
        if last.elapsed() < Duration::from_millis(200) {
            return;
        }
        last = Instant::now();
        STATUS_SHOWN.store(true, Ordering::Relaxed);
        let o = &s.odometry;
        use rollbase_control::service::ports::Limiting;
        let limit = match s.shaping.limiting {
            Limiting::None => String::new(),
            l @ (Limiting::Timeout | Limiting::Stop) => format!("  halting: {}", l.name()),
            l => format!("  slowed by {}", l.name()),
        };
        let reason = s.reason.map(|r| format!("  {r}")).unwrap_or_default();
        // One write under the lock: a log line cannot land in the middle of it.
        let text = format!(
            "\r\x1b[2Kx {:+.2} y {:+.2} θ {:+6.1}°  v ({:+.2}, {:+.2}) ω {:+.2}  legs {:.3}  {}{}{}   (Esc quits)",
            o.pose.x,
            o.pose.y,
            o.pose.theta.to_degrees(),
            o.twist.vx,
            o.twist.vy,
            o.twist.omega,
            s.joints[0].leg,
            s.state.name(),
            limit,
            reason
        );
        let mut e = std::io::stderr().lock();
        let _ = e.write_all(text.as_bytes());
        let _ = e.flush();
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_decode_to_commands() {
        let k = decode(b"w\x1b[Dq+ r");
        assert_eq!(k.len(), 6);
        assert!(matches!(k[0], Key::Move(t) if t.vx > 0.0));
        assert!(matches!(k[1], Key::Move(t) if t.vy > 0.0), "left arrow");
        assert!(matches!(k[2], Key::Move(t) if t.omega > 0.0));
        assert_eq!(k[3], Key::Legs(1.0));
        assert_eq!(k[4], Key::Stop);
        assert_eq!(k[5], Key::Rearm);
        assert_eq!(decode(b"\x1b"), vec![Key::Quit]);
        assert!(decode(b"xyz").is_empty());
    }
}
