//! `rollbase`: the command line of the rollbase CAN driver and control stack.
//!
//! Every command has `--help`; every failure prints what went wrong and what to do, and exits
//! non-zero. See README.md for the two first commands (the demo and the tests).

mod app;
mod bridge;
mod monitor_json;

use clap::Parser;
use std::io::Write as _;

/// Installs the log subscriber: `tracing` events go to stderr, filtered by `RUST_LOG`
/// (default `info`; e.g. `RUST_LOG=debug` adds one line per client event of the bridge).
/// The DDS stack's `log` records (rustdds) are bridged into the same output (tracing-log),
/// under their module paths, at `error` unless `RUST_LOG` names `rustdds`:
/// `RUST_LOG=info,rustdds=warn` shows its warnings (on a loopback without multicast it warns
/// about its own built-in readers many times a second, hence the quiet default).
/// Writing never fails the program: the fmt layer drops lines stderr does not take (a closed
/// pipe, a full disk) and, with `log_internal_errors(false)`, does not report that on stderr
/// either (that report would itself fail). Calling it twice is harmless.
pub fn init_logging() {
    use std::io::IsTerminal as _;
    use tracing_subscriber::EnvFilter;
    const DEFAULT: &str = "info,rustdds=error";
    let value = std::env::var("RUST_LOG").unwrap_or_default();
    let (filter, bad) = match EnvFilter::try_from_default_env() {
        Ok(f) if value.contains("rustdds") => (f, None),
        Ok(_) if value.trim().is_empty() => (EnvFilter::new(DEFAULT), None),
        Ok(f) => match "rustdds=error".parse() {
            Ok(d) => (f.add_directive(d), None),
            Err(_) => (f, None),
        },
        Err(e) => (
            EnvFilter::new(DEFAULT),
            std::env::var("RUST_LOG").ok().map(|v| (v, e)),
        ),
    };
    let installed = tracing_subscriber::fmt()
        .with_env_filter(filter)
        // stderr; a line of its own beside `demo --teleop`'s status line.
        .with_writer(app::log_writer)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false)
        .log_internal_errors(false)
        .try_init()
        .is_ok();
    if let (true, Some((value, e))) = (installed, bad) {
        // An empty RUST_LOG is "unset", not an error worth a line.
        if !value.trim().is_empty() {
            tracing::warn!("RUST_LOG={value:?} is not a valid filter ({e}); logging at {DEFAULT}");
        }
    }
}

/// glibc's malloc raises its mmap threshold to the size of each large block freed (up to
/// 32 MiB) and its trim threshold to twice that: after one large transient buffer (a 32 MB
/// ROS 2 message: rustdds reassembles it, the node decodes it), later buffers of that size
/// come from the heap and stay with the process when freed — its memory grew for good
/// (issue 27, finding 8). Fixed thresholds keep the default behaviour for small blocks and
/// return every block of 128 KiB or more to the system when it is freed.
fn fixed_malloc_thresholds() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 128 * 1024);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 * 1024);
    }
}

fn main() {
    fixed_malloc_thresholds();
    // A closed stdout or stderr must never kill a run (it would lose its recording): SIGPIPE
    // is ignored and every write checks its own result (`app::outln!` and friends; a filter
    // command like `rollbase dbc | head` ends quietly when its reader goes away).
    // SAFETY: setting a signal disposition at start-up, before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_IGN);
        // Likewise a file-size limit (`ulimit -f`): a write past it fails with EFBIG ("File
        // too large"), a recording failure the run reports and stops on, instead of SIGXFSZ
        // killing the process with its recording unfinished.
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
        // SIGUSR1 and SIGUSR2 mean nothing to rollbase; their default action would end the
        // process without a controlled stop (and lose the recording's index).
        libc::signal(libc::SIGUSR1, libc::SIG_IGN);
        libc::signal(libc::SIGUSR2, libc::SIG_IGN);
    }
    init_logging();
    let cli = app::Cli::parse();
    match app::run(cli) {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            let mut w = std::io::stderr().lock();
            let _ = writeln!(w, "error: {e}");
            let mut src = std::error::Error::source(&e);
            while let Some(s) = src {
                let _ = writeln!(w, "  caused by: {s}");
                src = s.source();
            }
            std::process::exit(app::exit::REFUSED);
        }
    }
}
