//! Fuzz target: the socketcand protocol as the server (`rollbase bridge`) reads it.
//!
//! The input is what a client sends, cut into TCP reads of varying sizes (the sizes come
//! from the input's first bytes). Every read goes through the bridge's own path: `Framer` →
//! `parse_element` → `ServerSession::handle`. Checked on every element:
//! - nothing panics, and the framer never holds more than one element's worth of bytes;
//! - every reply is exactly one `< … >` element of bounded length;
//! - the mode only moves forward (no channel → channel open → raw mode), a channel is opened
//!   at most once and its name passes `check_channel`;
//! - a frame to send formats back to a `send` element that parses to the same frame, and the
//!   `< frame … >` element the bridge forwards for it decodes on the client side to the
//!   same frame.
//!
//! Run: `cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run socketcand_server` (see README).
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_driver::bus::socketcand::{
    check_channel, format_frame_into, format_send_into, parse_element, ClientDecoder, Element,
    Framer, ServerAction, ServerMode, ServerSession, MAX_ELEMENT_LEN,
};
use rollbase_driver::frame::TimestampedFrame;
use std::time::Duration;

fn rank(m: ServerMode) -> u8 {
    match m {
        ServerMode::NoBus => 0,
        ServerMode::Bcm => 1,
        ServerMode::Raw => 2,
    }
}

fuzz_target!(|input: &[u8]| {
    let (sizes, data) = input.split_at(input.len().min(8));
    let mut framer = Framer::new();
    let mut session = ServerSession::new();
    let mut opened = 0usize;
    let mut elements = 0usize;
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
        framer.extend(chunk);
        while let Some(r) = framer.next_element() {
            elements += 1;
            assert!(elements <= data.len(), "more elements than bytes");
            let before = session.mode();
            let step = session.handle(r.and_then(parse_element));
            assert!(rank(session.mode()) >= rank(before), "mode went back");
            if let Some(reply) = &step.reply {
                assert!(reply.len() <= 512, "reply of {} bytes", reply.len());
                assert!(
                    reply.starts_with("< ") && reply.ends_with(" >"),
                    "{reply:?}"
                );
                assert_eq!(reply.matches('<').count(), 1, "{reply:?}");
                assert_eq!(reply.matches('>').count(), 1, "{reply:?}");
            }
            match step.action {
                ServerAction::Open(ch) => {
                    opened += 1;
                    assert_eq!(opened, 1, "a second channel opened");
                    assert_eq!(before, ServerMode::NoBus);
                    assert!(check_channel(&ch).is_ok(), "{ch:?}");
                    assert_eq!(step.reply.as_deref(), Some("< ok >"));
                }
                ServerAction::EnterRaw => {
                    assert_eq!(before, ServerMode::Bcm);
                    assert_eq!(session.mode(), ServerMode::Raw);
                }
                ServerAction::Send(frame) => {
                    assert_ne!(before, ServerMode::NoBus);
                    assert!(step.reply.is_none());
                    text.clear();
                    format_send_into(&mut text, &frame);
                    assert_eq!(parse_element(&text), Ok(Element::Send(frame)), "{text}");
                    // What the bridge forwards for it, as a client decodes it.
                    let tf = TimestampedFrame {
                        timestamp: Duration::new(1_700_000_000, 123_456_000),
                        frame,
                    };
                    text.clear();
                    format_frame_into(&mut text, &tf);
                    let mut client = ClientDecoder::new();
                    client.extend(text.as_bytes());
                    assert_eq!(client.next_frame(), Ok(Some(tf)), "{text}");
                }
                ServerAction::None => {}
            }
        }
        assert!(
            framer.buffered() <= MAX_ELEMENT_LEN,
            "{} bytes buffered",
            framer.buffered()
        );
    }
});
