//! A sans-IO SDO client for one transfer at a time, expedited or segmented (CiA 301
//! 7.2.4.3.2–7): what `rollbase sdo` uses to read and write any object of a device,
//! including strings longer than 4 bytes (0x1008 device name …).
//!
//! ```text
//!  upload:   initiate (0x40) ──► expedited answer (0x43…0x4F): done
//!                            └─► segmented answer (0x41 + size): segment requests 0x60/0x70
//!                                (toggle alternating) ──► segments (7 bytes, c = last)
//!  download: ≤ 4 bytes: expedited initiate (0x23…0x2F) ──► 0x60: done
//!            longer: initiate with size (0x21) ──► 0x60, then segments (0x00/0x10 | n | c)
//!                    ──► acknowledgements (0x20/0x30, toggle echoed)
//! ```
//!
//! Every step checks the command specifier, the object and the toggle bit; an abort from the
//! server is a typed [`AbortCode`]. Nothing here allocates per frame beyond the value being
//! transferred, which is bounded by [`MAX_TRANSFER`].

use super::cob;
use super::sdo::AbortCode;
use crate::frame::CanFrame;

/// Largest value a transfer carries (bytes): more is refused, not buffered.
pub const MAX_TRANSFER: usize = 65_536;

/// Why a transfer failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SdoClientError {
    /// The server aborted the transfer.
    #[error("the device aborted the transfer of 0x{index:04X}:{sub:02X}: {code}")]
    Aborted {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The device's abort code.
        code: AbortCode,
    },
    /// The server answered something the protocol does not allow here.
    #[error("unexpected SDO response (command byte 0x{cs:02X}) while {during}")]
    Protocol {
        /// The command byte received.
        cs: u8,
        /// What the client was waiting for.
        during: &'static str,
    },
    /// A segment came with the wrong toggle bit.
    #[error("SDO segment with the wrong toggle bit (a segment was lost or repeated)")]
    Toggle,
    /// The value is longer than [`MAX_TRANSFER`] (or than the size the server announced).
    #[error("the value is longer than {0} bytes")]
    TooLong(usize),
}

/// What the caller does after a response.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Step {
    /// Send this request and wait for the next response.
    Send(CanFrame),
    /// The transfer is complete: the value read (empty for a download).
    Done(Vec<u8>),
    /// The frame was not this transfer's response (another node or id): keep waiting.
    Ignore,
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum State {
    UploadInitiate,
    UploadSegments { toggle: u8, size: Option<usize> },
    DownloadInitiate { segmented: bool },
    DownloadSegments { toggle: u8, last_sent: bool },
    Done,
}

/// One SDO transfer with one server.
#[derive(Clone, Debug)]
pub struct SdoClient {
    node: u8,
    index: u16,
    sub: u8,
    state: State,
    buf: Vec<u8>,
    pos: usize,
}

fn frame(node: u8, d: [u8; 8]) -> CanFrame {
    CanFrame::new(cob::sdo_rx(node), &d).unwrap_or_else(|_| unreachable!("SDO frames are valid"))
}

fn head(cs: u8, index: u16, sub: u8) -> [u8; 8] {
    let i = index.to_le_bytes();
    [cs, i[0], i[1], sub, 0, 0, 0, 0]
}

impl SdoClient {
    /// Starts reading `index:sub` of `node`: returns the client and the first request.
    pub fn upload(node: u8, index: u16, sub: u8) -> (Self, CanFrame) {
        let c = Self {
            node,
            index,
            sub,
            state: State::UploadInitiate,
            buf: Vec::new(),
            pos: 0,
        };
        (c, frame(node, head(0x40, index, sub)))
    }

    /// Starts writing `data` to `index:sub` of `node` (expedited up to 4 bytes, segmented
    /// beyond): returns the client and the first request, or `TooLong`.
    pub fn download(
        node: u8,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(Self, CanFrame), SdoClientError> {
        if data.len() > MAX_TRANSFER {
            return Err(SdoClientError::TooLong(MAX_TRANSFER));
        }
        let mut d = head(0x21, index, sub);
        let segmented = data.is_empty() || data.len() > 4;
        if segmented {
            // Size indicated (s = 1), not expedited.
            d[4..8].copy_from_slice(&(data.len() as u32).to_le_bytes());
        } else {
            d[0] = 0x23 | (((4 - data.len()) as u8) << 2);
            d[4..4 + data.len()].copy_from_slice(data);
        }
        let c = Self {
            node,
            index,
            sub,
            state: State::DownloadInitiate { segmented },
            buf: data.to_vec(),
            pos: 0,
        };
        Ok((c, frame(node, d)))
    }

    /// The object of the transfer.
    pub fn object(&self) -> (u16, u8) {
        (self.index, self.sub)
    }

    /// True once the transfer completed.
    pub fn done(&self) -> bool {
        self.state == State::Done
    }

    /// The abort request that ends the transfer early (e.g. after a timeout).
    pub fn abort_frame(&self, code: AbortCode) -> CanFrame {
        let mut d = head(0x80, self.index, self.sub);
        d[4..8].copy_from_slice(&code.code().to_le_bytes());
        frame(self.node, d)
    }

    fn next_segment(&mut self, toggle: u8) -> CanFrame {
        let n = (self.buf.len() - self.pos).min(7);
        let last = self.pos + n >= self.buf.len();
        let mut d = [0u8; 8];
        d[0] = (toggle << 4) | (((7 - n) as u8) << 1) | u8::from(last);
        d[1..1 + n].copy_from_slice(&self.buf[self.pos..self.pos + n]);
        self.pos += n;
        self.state = State::DownloadSegments {
            toggle,
            last_sent: last,
        };
        frame(self.node, d)
    }

    /// Takes a received frame; see [`Step`].
    pub fn on_frame(&mut self, f: &CanFrame) -> Result<Step, SdoClientError> {
        if f.id() != cob::sdo_tx(self.node) || f.len() != 8 {
            return Ok(Step::Ignore);
        }
        let d = f.data();
        let cs = d[0];
        let index = u16::from_le_bytes([d[1], d[2]]);
        if cs == 0x80 {
            let code = AbortCode::from_code(u32::from_le_bytes([d[4], d[5], d[6], d[7]]));
            self.state = State::Done;
            return Err(SdoClientError::Aborted {
                index: self.index,
                sub: self.sub,
                code,
            });
        }
        let same_object = index == self.index && d[3] == self.sub;
        let proto = |during| SdoClientError::Protocol { cs, during };
        match self.state.clone() {
            State::UploadInitiate => {
                if cs >> 5 != 2 || !same_object {
                    return Err(proto("waiting for the upload's first answer"));
                }
                if cs & 0x02 != 0 {
                    let n = if cs & 0x01 != 0 {
                        4 - usize::from((cs >> 2) & 3)
                    } else {
                        4
                    };
                    self.state = State::Done;
                    return Ok(Step::Done(d[4..4 + n].to_vec()));
                }
                let size =
                    (cs & 0x01 != 0).then(|| u32::from_le_bytes([d[4], d[5], d[6], d[7]]) as usize);
                if size.is_some_and(|s| s > MAX_TRANSFER) {
                    return Err(SdoClientError::TooLong(MAX_TRANSFER));
                }
                self.state = State::UploadSegments { toggle: 0, size };
                Ok(Step::Send(frame(self.node, [0x60, 0, 0, 0, 0, 0, 0, 0])))
            }
            State::UploadSegments { toggle, size } => {
                if cs >> 5 != 0 {
                    return Err(proto("waiting for an upload segment"));
                }
                if (cs >> 4) & 1 != toggle {
                    return Err(SdoClientError::Toggle);
                }
                let n = 7 - usize::from((cs >> 1) & 7);
                self.buf.extend_from_slice(&d[1..1 + n]);
                let limit = size.unwrap_or(MAX_TRANSFER).min(MAX_TRANSFER);
                if self.buf.len() > limit {
                    return Err(SdoClientError::TooLong(limit));
                }
                if cs & 0x01 != 0 {
                    self.state = State::Done;
                    return Ok(Step::Done(std::mem::take(&mut self.buf)));
                }
                let t = toggle ^ 1;
                self.state = State::UploadSegments { toggle: t, size };
                Ok(Step::Send(frame(
                    self.node,
                    [0x60 | (t << 4), 0, 0, 0, 0, 0, 0, 0],
                )))
            }
            State::DownloadInitiate { segmented } => {
                if cs != 0x60 || !same_object {
                    return Err(proto("waiting for the download's first answer"));
                }
                if !segmented {
                    self.state = State::Done;
                    return Ok(Step::Done(Vec::new()));
                }
                Ok(Step::Send(self.next_segment(0)))
            }
            State::DownloadSegments { toggle, last_sent } => {
                if cs & 0xEF != 0x20 {
                    return Err(proto("waiting for a download segment's answer"));
                }
                if (cs >> 4) & 1 != toggle {
                    return Err(SdoClientError::Toggle);
                }
                if last_sent {
                    self.state = State::Done;
                    return Ok(Step::Done(Vec::new()));
                }
                Ok(Step::Send(self.next_segment(toggle ^ 1)))
            }
            State::Done => Ok(Step::Ignore),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resp(node: u8, d: [u8; 8]) -> CanFrame {
        CanFrame::new(cob::sdo_tx(node), &d).unwrap()
    }

    #[test]
    fn segmented_upload_of_a_device_name() {
        // "rollbase!" (9 bytes): initiate 0x41 size 9, segments 0x00 (7 bytes), 0x1B (2 bytes,
        // n = 5, c = 1, toggle 1).
        let (mut c, f) = SdoClient::upload(5, 0x1008, 0);
        assert_eq!(
            (f.id(), f.data()),
            (0x605, &[0x40, 0x08, 0x10, 0, 0, 0, 0, 0][..])
        );
        let s = c
            .on_frame(&resp(5, [0x41, 0x08, 0x10, 0, 9, 0, 0, 0]))
            .unwrap();
        assert_eq!(s, Step::Send(frame(5, [0x60, 0, 0, 0, 0, 0, 0, 0])));
        let s = c
            .on_frame(&resp(5, [0x00, b'r', b'o', b'l', b'l', b'b', b'a', b's']))
            .unwrap();
        assert_eq!(s, Step::Send(frame(5, [0x70, 0, 0, 0, 0, 0, 0, 0])));
        let s = c
            .on_frame(&resp(5, [0x1B, b'e', b'!', 0, 0, 0, 0, 0]))
            .unwrap();
        assert_eq!(s, Step::Done(b"rollbase!".to_vec()));
        assert!(c.done());
    }

    #[test]
    fn segmented_download_and_its_acknowledgements() {
        let data = b"left front steer"; // 16 bytes: 7 + 7 + 2
        let (mut c, f) = SdoClient::download(3, 0x2000, 0, data).unwrap();
        assert_eq!(f.data(), &[0x21, 0x00, 0x20, 0, 16, 0, 0, 0]);
        let Step::Send(s1) = c
            .on_frame(&resp(3, [0x60, 0x00, 0x20, 0, 0, 0, 0, 0]))
            .unwrap()
        else {
            panic!()
        };
        assert_eq!(s1.data(), &[0x00, b'l', b'e', b'f', b't', b' ', b'f', b'r']);
        let Step::Send(s2) = c.on_frame(&resp(3, [0x20, 0, 0, 0, 0, 0, 0, 0])).unwrap() else {
            panic!()
        };
        assert_eq!(s2.data(), &[0x10, b'o', b'n', b't', b' ', b's', b't', b'e']);
        let Step::Send(s3) = c.on_frame(&resp(3, [0x30, 0, 0, 0, 0, 0, 0, 0])).unwrap() else {
            panic!()
        };
        // Last segment: 2 bytes, n = 5, c = 1, toggle 0: 0x0B.
        assert_eq!(s3.data(), &[0x0B, b'e', b'r', 0, 0, 0, 0, 0]);
        assert_eq!(
            c.on_frame(&resp(3, [0x20, 0, 0, 0, 0, 0, 0, 0])).unwrap(),
            Step::Done(Vec::new())
        );
    }

    #[test]
    fn expedited_both_ways_aborts_and_toggle_errors() {
        let (mut c, f) = SdoClient::download(1, 0x6060, 0, &[9]).unwrap();
        assert_eq!(f.data(), &[0x2F, 0x60, 0x60, 0, 9, 0, 0, 0]);
        assert_eq!(
            c.on_frame(&resp(1, [0x60, 0x60, 0x60, 0, 0, 0, 0, 0]))
                .unwrap(),
            Step::Done(Vec::new())
        );
        let (mut c, _) = SdoClient::upload(1, 0x6041, 0);
        assert_eq!(c.on_frame(&resp(2, [0; 8])).unwrap(), Step::Ignore);
        assert_eq!(
            c.on_frame(&resp(1, [0x4B, 0x41, 0x60, 0, 0x37, 0x06, 0, 0]))
                .unwrap(),
            Step::Done(vec![0x37, 0x06])
        );
        let (mut c, _) = SdoClient::upload(1, 0x1234, 0);
        assert_eq!(
            c.on_frame(&resp(1, [0x80, 0x34, 0x12, 0, 0, 0, 2, 6])),
            Err(SdoClientError::Aborted {
                index: 0x1234,
                sub: 0,
                code: AbortCode::NoObject
            })
        );
        let (mut c, _) = SdoClient::upload(1, 0x1008, 0);
        c.on_frame(&resp(1, [0x41, 0x08, 0x10, 0, 20, 0, 0, 0]))
            .unwrap();
        assert_eq!(
            c.on_frame(&resp(1, [0x10, 1, 2, 3, 4, 5, 6, 7])),
            Err(SdoClientError::Toggle)
        );
    }

    proptest::proptest! {
        /// Any response bytes end in a step or a typed error, never a panic.
        #[test]
        fn arbitrary_responses_never_panic(bytes in proptest::collection::vec(proptest::array::uniform8(proptest::num::u8::ANY), 1..20), up in proptest::bool::ANY) {
            let mut c = if up {
                SdoClient::upload(1, 0x1008, 0).0
            } else {
                SdoClient::download(1, 0x2000, 0, &[7u8; 20]).unwrap().0
            };
            for d in bytes {
                if c.on_frame(&resp(1, d)).is_err() {
                    break;
                }
            }
        }
    }
}
