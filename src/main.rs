//! `rollbase`: the command line of the rollbase CAN driver and control stack.
//!
//! Every command has `--help`; every failure prints what went wrong and what to do, and exits
//! non-zero. See README.md for the two first commands (the demo and the tests).

mod app;
mod bridge;
mod monitor_json;

use clap::Parser;

fn main() {
    // Behave like a Unix filter: when stdout is closed early (`rollbase dbc | head`), end
    // quietly instead of panicking on the failed write.
    // SAFETY: restoring the default disposition of SIGPIPE at start-up, before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = app::Cli::parse();
    match app::run(cli) {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {e}");
            let mut src = std::error::Error::source(&e);
            while let Some(s) = src {
                eprintln!("  caused by: {s}");
                src = s.source();
            }
            std::process::exit(2);
        }
    }
}
