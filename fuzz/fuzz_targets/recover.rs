//! Fuzz target: `rollbase recover` on arbitrary bytes (a damaged or hostile recording).
//!
//! The input, prefixed with the MCAP magic (anything else is refused at once), goes through
//! `record::recover_bytes` into an in-memory file. Checked on every input:
//! - nothing panics, and no allocation exceeds libFuzzer's limit (every length is checked
//!   against the bytes that are there before anything is taken);
//! - when it succeeds, the output is a complete MCAP file that mcap's own reader reads with
//!   chunk CRCs checked, holding exactly the messages the report counts, per topic;
//! - every skipped region lies inside the input.
//!
//! Run: `cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run recover` (see README).
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::collections::BTreeMap;
use std::io::Cursor;

fuzz_target!(|data: &[u8]| {
    let mut input = Vec::with_capacity(data.len() + 8);
    input.extend_from_slice(mcap::MAGIC);
    input.extend_from_slice(data);
    let Ok((report, out)) =
        rollbase::record::recover_bytes(&input, Cursor::new(Vec::new()), "fuzz.mcap")
    else {
        return;
    };
    for s in &report.skipped {
        assert!(s.offset + s.length <= input.len() as u64, "{s:?}");
    }
    let bytes = out.into_inner();
    let opts = mcap::read::Options::ValidateChunkCrcs.into();
    let stream = mcap::MessageStream::new_with_options(&bytes, opts).expect("a valid MCAP file");
    let mut per_topic: BTreeMap<String, u64> = BTreeMap::new();
    for m in stream {
        let m = m.expect("every message of the output reads");
        *per_topic.entry(m.channel.topic.clone()).or_default() += 1;
    }
    assert_eq!(per_topic, report.messages);
});
