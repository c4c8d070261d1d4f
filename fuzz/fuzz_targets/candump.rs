//! Fuzz target: the `candump -L` log parser.
//!
//! The input bytes are read as a log file through `CandumpReader` (must not panic on any
//! bytes, including invalid UTF-8, and must report line numbers that only grow). Every line
//! that parses is formatted again and must parse again to the same frame and interface, and
//! the second formatting must equal the first (formatting is a fixed point of
//! parse ∘ format).
//!
//! Run: `cargo +nightly fuzz run candump` from the repository root.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_driver::candump::{format_line_with_kind, parse_line_with_kind, CandumpReader};

fuzz_target!(|input: &[u8]| {
    let mut reader = CandumpReader::new(input);
    let mut last_line = 0usize;
    let mut items = 0usize;
    while let Some(item) = reader.next() {
        assert!(reader.line() > last_line, "line numbers must grow");
        last_line = reader.line();
        items += 1;
        assert!(items <= input.len() + 1, "more items than input bytes");
        let _ = item;
    }
    // Line-level round trip on every UTF-8 line of the input.
    let Ok(text) = std::str::from_utf8(input) else {
        return;
    };
    for line in text.lines() {
        if let Ok((entry, kind)) = parse_line_with_kind(line) {
            let once = format_line_with_kind(&entry, kind);
            let (again, kind2) =
                parse_line_with_kind(&once).expect("a formatted entry must parse again");
            assert_eq!(kind, kind2);
            assert_eq!(entry.frame, again.frame);
            assert_eq!(entry.interface, again.interface);
            assert_eq!(format_line_with_kind(&again, kind2), once);
        }
    }
});
