//! Fuzz target: the socketcand protocol as the client (`SocketcandBus`) reads it.
//!
//! The input is what a server sends, cut into TCP reads of varying sizes (the sizes come from
//! the input's first bytes), decoded by `ClientDecoder` — the exact code `SocketcandBus`
//! runs on every received byte. Checked:
//! - nothing panics; after the decoder asks for more bytes it holds at most one element's
//!   worth;
//! - every frame it returns formats back (`< frame … >`, socketcand's format) to an element
//!   that decodes to the same frame, with the timestamp cut to microseconds;
//! - the counters add up: frames returned, skipped, error elements and malformed elements
//!   are each counted once, never more than there were bytes.
//!
//! Run: `cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run socketcand_client` (see README).
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_driver::bus::socketcand::{
    format_frame_into, ClientDecodeError, ClientDecoder, MAX_ELEMENT_LEN,
};
use rollbase_driver::frame::TimestampedFrame;
use std::time::Duration;

fuzz_target!(|input: &[u8]| {
    let (sizes, data) = input.split_at(input.len().min(8));
    let mut dec = ClientDecoder::new();
    let (mut frames, mut errors, mut malformed) = (0u64, 0u64, 0u64);
    let mut text = String::new();
    let mut rest = data;
    let mut i = 0usize;
    while !rest.is_empty() {
        let n = sizes
            .get(i % sizes.len().max(1))
            .map_or(rest.len(), |&s| 1 + usize::from(s))
            .min(rest.len());
        i += 1;
        let (chunk, tail) = rest.split_at(n);
        rest = tail;
        dec.extend(chunk);
        loop {
            match dec.next_frame() {
                Ok(None) => break,
                Ok(Some(tf)) => {
                    frames += 1;
                    text.clear();
                    format_frame_into(&mut text, &tf);
                    let mut again = ClientDecoder::new();
                    again.extend(text.as_bytes());
                    let want = TimestampedFrame {
                        timestamp: Duration::new(
                            tf.timestamp.as_secs(),
                            tf.timestamp.subsec_micros() * 1000,
                        ),
                        frame: tf.frame,
                    };
                    assert_eq!(again.next_frame(), Ok(Some(want)), "{text}");
                }
                Err(ClientDecodeError::ErrorElement(msg)) => {
                    errors += 1;
                    assert!(!msg.contains('>'), "{msg:?}");
                }
                Err(ClientDecodeError::Malformed(_)) => malformed += 1,
            }
            let total = frames + errors + malformed + dec.stats().skipped;
            assert!(total <= data.len() as u64, "more elements than bytes");
        }
        assert!(
            dec.buffered() <= MAX_ELEMENT_LEN,
            "{} bytes buffered",
            dec.buffered()
        );
    }
    let s = dec.stats();
    assert_eq!(
        (s.frames_in, s.error_elements, s.malformed, s.frames_out),
        (frames, errors, malformed, 0)
    );
});
