//! `rollbase`: the command line of the rollbase CAN driver and control stack.
//!
//! Every command has `--help`; every failure prints what went wrong and what to do, and exits
//! non-zero. See README.md for the two first commands (the demo and the tests).

mod app;
mod bridge;
mod monitor_json;

use clap::Parser;

fn main() {
    // A closed stdout or stderr must never kill a run (it would lose its recording): SIGPIPE
    // is ignored and every write checks its own result (`app::outln!` and friends; a filter
    // command like `rollbase dbc | head` ends quietly when its reader goes away).
    // SAFETY: setting a signal disposition at start-up, before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_IGN);
    }
    app::init_logging();
    let cli = app::Cli::parse();
    match app::run(cli) {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            use std::io::Write;
            let mut w = std::io::stderr();
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
