//! Decodes a `candump -L` capture from stdin through the protocol receiver and prints one
//! line per frame plus the statistics:
//! `candump -L vcan0 | cargo run -p rollbase-driver --example decode_log`.
use std::io;

use rollbase_driver::candump::{describe, CandumpReader, MonitorStats};
use rollbase_driver::rx::Receiver;

fn main() {
    let stdin = io::stdin();
    let mut rx = Receiver::new();
    let mut stats = MonitorStats::default();
    for item in CandumpReader::new(stdin.lock()) {
        match item {
            Ok(e) => println!("{}", describe(&mut rx, &mut stats, e.timestamp, &e.frame)),
            Err(e) => {
                stats.unparsable += 1;
                eprintln!("{e}");
            }
        }
    }
    println!("{stats}");
}
