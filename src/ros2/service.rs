//! Service requests from every ROS 2 caller, whichever rmw it runs on.
//!
//! ROS 2's rmw layers put a service on two DDS topics (`rq/<service>Request`,
//! `rr/<service>Reply`) but correlate a reply with its request differently:
//!
//! - **rmw_cyclonedds_cpp** ("cyclone"): the request payload starts with a 16-byte header, the
//!   client's 64-bit id and the request's 64-bit sequence number; the reply starts with the
//!   same 16 bytes, which is how the client recognises its reply.
//! - **rmw_fastrtps_cpp** (Fast DDS, ROS 2's default rmw) and rmw_connextdds ("enhanced", the
//!   OMG RPC-over-DDS enhanced mapping): the payload is the request alone; the reply carries the
//!   request's identity in the RTPS inline QoS parameter `related_sample_identity`. rmw_fastrtps
//!   (Humble and newer) also sends that parameter with the request, its writer GUID set to the
//!   client's reply reader, and takes the reply whose related identity names that reader (or
//!   its request writer, as older releases did) with the request's sequence number.
//!
//! ros2-client's `Server` decodes every request with one mapping fixed when the server is
//! created, so one process could not serve both kinds of caller. rollbase reads the request
//! topic as raw bytes instead and decides per request ([`decode_request`]):
//!
//! 1. the payload is decoded both ways; a layout that does not take the payload to its last
//!    byte (up to 3 bytes of end padding) is not the caller's;
//! 2. if only one layout fits, it is the caller's (for `std_srvs/Trigger` the lengths alone
//!    differ: 1 byte against 17);
//! 3. if both fit (a request type whose first 16 bytes could be a header), the inline
//!    `related_sample_identity` decides: present → enhanced (rmw_fastrtps always sends it),
//!    absent → cyclone;
//! 4. if neither fits, the request is undecodable: counted and logged with the reason.
//!
//! `--ros2-service-mapping cyclone|enhanced` skips the detection (a request that does not
//! fit the forced mapping is undecodable). The reply goes back in the caller's mapping
//! ([`ReplyTo`]).

use super::msg::{self, RosMsg};
use super::ServiceMapping;

/// What the DDS layer knows of a received request sample besides its payload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RequestMeta {
    /// GUID of the writer that sent it (the client's request writer).
    pub writer_guid: [u8; 16],
    /// Its RTPS sequence number.
    pub sequence_number: i64,
    /// The inline QoS `related_sample_identity` (writer GUID, sequence number), if sent.
    pub related: Option<([u8; 16], i64)>,
}

/// How to address the reply.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReplyTo {
    /// rmw_cyclonedds: the reply payload starts with these 16 bytes (the request's header,
    /// little endian).
    Cyclone {
        /// Client id and sequence number, as the client sent them.
        header: [u8; 16],
    },
    /// Enhanced mapping: the reply's `related_sample_identity`.
    Enhanced {
        /// The GUID the client recognises (its reply reader, or its request writer).
        writer_guid: [u8; 16],
        /// The request's sequence number.
        sequence_number: i64,
    },
}

impl ReplyTo {
    /// The mapping this reply uses.
    pub fn mapping(&self) -> ServiceMapping {
        match self {
            Self::Cyclone { .. } => ServiceMapping::Cyclone,
            Self::Enhanced { .. } => ServiceMapping::Enhanced,
        }
    }
}

/// A decoded request and where its reply goes.
#[derive(Clone, Debug, PartialEq)]
pub struct Request<T> {
    /// The request.
    pub request: T,
    /// The caller's mapping and identity.
    pub reply_to: ReplyTo,
}

/// The GUID_UNKNOWN of RTPS (all zero).
const GUID_UNKNOWN: [u8; 16] = [0; 16];

/// Decodes `payload` as exactly one `T` (up to 3 bytes of end padding after it).
fn exact<T: RosMsg>(payload: &[u8], big_endian: bool) -> Result<T, String> {
    let (v, used) = msg::from_cdr_payload::<T>(payload, big_endian).map_err(|e| e.to_string())?;
    match payload.len() - used {
        0..=3 => Ok(v),
        left => Err(format!(
            "{left} bytes left after a {} of {used} bytes",
            T::DEF.name
        )),
    }
}

/// The cyclone layout: a 16-byte header, then exactly one `T`.
fn cyclone<T: RosMsg>(payload: &[u8], big_endian: bool) -> Result<(T, [u8; 16]), String> {
    if payload.len() < 16 {
        return Err(format!(
            "{} bytes: shorter than the 16-byte request header",
            payload.len()
        ));
    }
    let mut header = [0u8; 16];
    header.copy_from_slice(&payload[..16]);
    if big_endian {
        // The reply is written little endian: the header's two 64-bit fields are swapped so
        // that the client reads back the values it sent.
        header[..8].reverse();
        header[8..].reverse();
    }
    // The header is 8-aligned, so the request's alignment counts from its own start.
    exact::<T>(&payload[16..], big_endian).map(|v| (v, header))
}

/// Decodes a service request of type `T` in the caller's mapping (see the module docs).
/// `mapping` is the `--ros2-service-mapping` option (`Auto` detects). The error says why no
/// mapping fits.
pub fn decode_request<T: RosMsg>(
    payload: &[u8],
    big_endian: bool,
    meta: &RequestMeta,
    mapping: ServiceMapping,
) -> Result<Request<T>, String> {
    let enhanced_reply = || {
        let writer_guid = match meta.related {
            Some((g, _)) if g != GUID_UNKNOWN => g,
            _ => meta.writer_guid,
        };
        ReplyTo::Enhanced {
            writer_guid,
            sequence_number: meta.sequence_number,
        }
    };
    let as_cyclone = || {
        cyclone::<T>(payload, big_endian).map(|(request, header)| Request {
            request,
            reply_to: ReplyTo::Cyclone { header },
        })
    };
    let as_enhanced = || {
        exact::<T>(payload, big_endian).map(|request| Request {
            request,
            reply_to: enhanced_reply(),
        })
    };
    match mapping {
        ServiceMapping::Cyclone => {
            as_cyclone().map_err(|e| format!("not a request in the cyclone mapping: {e}"))
        }
        ServiceMapping::Enhanced => {
            as_enhanced().map_err(|e| format!("not a request in the enhanced mapping: {e}"))
        }
        ServiceMapping::Auto => match (as_cyclone(), as_enhanced()) {
            (Ok(c), Err(_)) => Ok(c),
            (Err(_), Ok(e)) => Ok(e),
            (Ok(c), Ok(e)) => Ok(if meta.related.is_some() { e } else { c }),
            (Err(c), Err(e)) => Err(format!(
                "{} bytes fit neither mapping: as cyclone (rmw_cyclonedds: 16-byte header + request): {c}; as enhanced (rmw_fastrtps: request alone): {e}",
                payload.len()
            )),
        },
    }
}

/// A sample identity: writer GUID and sequence number.
pub type SampleId = ([u8; 16], i64);

/// The reply's CDR payload (little endian, without the encapsulation header) and the
/// `related_sample_identity` to send with it, for `reply_to`.
pub fn encode_reply<T: RosMsg>(
    reply: &T,
    reply_to: &ReplyTo,
) -> Result<(Vec<u8>, Option<SampleId>), msg::MsgError> {
    let body = msg::to_cdr(reply)?;
    let body = &body[msg::CDR_LE_HEADER.len()..];
    Ok(match reply_to {
        ReplyTo::Cyclone { header } => {
            let mut out = Vec::with_capacity(16 + body.len());
            out.extend_from_slice(header);
            out.extend_from_slice(body);
            (out, None)
        }
        ReplyTo::Enhanced {
            writer_guid,
            sequence_number,
        } => (body.to_vec(), Some((*writer_guid, *sequence_number))),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msg::{TriggerRequest, TriggerResponse};

    const WRITER: [u8; 16] = [7; 16];
    const READER: [u8; 16] = [9; 16];

    fn meta(related: Option<([u8; 16], i64)>) -> RequestMeta {
        RequestMeta {
            writer_guid: WRITER,
            sequence_number: 42,
            related,
        }
    }

    /// rmw_cyclonedds' request: client id 0x1122334455667788, sequence 7 (little endian), then
    /// the Trigger request's placeholder byte.
    fn cyclone_trigger() -> Vec<u8> {
        let mut b = 0x1122334455667788u64.to_le_bytes().to_vec();
        b.extend_from_slice(&7i64.to_le_bytes());
        b.push(0);
        b
    }

    #[test]
    fn a_cyclone_request_is_answered_in_the_cyclone_mapping() {
        let r = decode_request::<TriggerRequest>(
            &cyclone_trigger(),
            false,
            &meta(None),
            ServiceMapping::Auto,
        )
        .unwrap();
        let header: [u8; 16] = cyclone_trigger()[..16].try_into().unwrap();
        assert_eq!(r.reply_to, ReplyTo::Cyclone { header });
        let resp = TriggerResponse {
            success: true,
            message: "ok".into(),
        };
        let (bytes, related) = encode_reply(&resp, &r.reply_to).unwrap();
        assert!(related.is_none());
        assert_eq!(
            &bytes[..16],
            &header,
            "the reply starts with the request's header"
        );
        let back: TriggerResponse = msg::from_cdr_payload(&bytes[16..], false).unwrap().0;
        assert_eq!(back, resp);
    }

    #[test]
    fn a_fast_dds_request_is_answered_in_the_enhanced_mapping() {
        // rmw_fastrtps: the request alone (padded to 4 bytes, as Fast DDS does), the related
        // identity naming the client's reply reader with an unknown sequence number.
        let unknown_sn = (u32::MAX as i64) << 32;
        for payload in [vec![0u8], vec![0u8, 0, 0, 0]] {
            let r = decode_request::<TriggerRequest>(
                &payload,
                false,
                &meta(Some((READER, unknown_sn))),
                ServiceMapping::Auto,
            )
            .unwrap();
            assert_eq!(
                r.reply_to,
                ReplyTo::Enhanced {
                    writer_guid: READER,
                    sequence_number: 42
                }
            );
            let (bytes, related) = encode_reply(&TriggerResponse::default(), &r.reply_to).unwrap();
            assert_eq!(related, Some((READER, 42)));
            assert_eq!(bytes.len(), 9, "bool, padding, an empty string: no header");
        }
        // An older client without the inline parameter: the reply names its request writer.
        let r = decode_request::<TriggerRequest>(&[0], false, &meta(None), ServiceMapping::Auto)
            .unwrap();
        assert_eq!(
            r.reply_to,
            ReplyTo::Enhanced {
                writer_guid: WRITER,
                sequence_number: 42
            }
        );
    }

    #[test]
    fn when_both_layouts_fit_the_inline_identity_decides() {
        // 27 bytes that are a Trigger_Response both alone (success, a 19-byte message) and
        // after a 16-byte header (success, "ok"): only the inline identity tells them apart.
        let mut p = vec![1u8, 0, 0, 0];
        p.extend_from_slice(&19u32.to_le_bytes());
        p.extend_from_slice(b"abcdefgh");
        p.extend_from_slice(&[1, 0, 0, 0]);
        p.extend_from_slice(&3u32.to_le_bytes());
        p.extend_from_slice(b"ok\0");
        assert_eq!(p.len(), 27);
        let c = decode_request::<TriggerResponse>(&p, false, &meta(None), ServiceMapping::Auto)
            .unwrap();
        assert_eq!(c.reply_to.mapping(), ServiceMapping::Cyclone);
        assert_eq!(c.request.message, "ok");
        let e = decode_request::<TriggerResponse>(
            &p,
            false,
            &meta(Some((READER, 1))),
            ServiceMapping::Auto,
        )
        .unwrap();
        assert_eq!(e.reply_to.mapping(), ServiceMapping::Enhanced);
        assert_eq!(e.request.message.len(), 18);
    }

    #[test]
    fn forced_mappings_and_undecodable_requests() {
        let e = decode_request::<TriggerRequest>(
            &cyclone_trigger(),
            false,
            &meta(None),
            ServiceMapping::Enhanced,
        )
        .unwrap_err();
        assert!(e.contains("enhanced"), "{e}");
        let e = decode_request::<TriggerRequest>(&[0], false, &meta(None), ServiceMapping::Cyclone)
            .unwrap_err();
        assert!(e.contains("cyclone") && e.contains("16-byte"), "{e}");
        for bad in [&[][..], &[0u8; 9][..], &[0u8; 40][..]] {
            let e = decode_request::<TriggerRequest>(bad, false, &meta(None), ServiceMapping::Auto)
                .unwrap_err();
            assert!(e.contains("fit neither mapping"), "{e}");
        }
    }

    #[test]
    fn a_big_endian_cyclone_header_is_echoed_in_little_endian() {
        let mut b = 0x1122334455667788u64.to_be_bytes().to_vec();
        b.extend_from_slice(&7i64.to_be_bytes());
        b.push(0);
        let r =
            decode_request::<TriggerRequest>(&b, true, &meta(None), ServiceMapping::Auto).unwrap();
        let mut expect = 0x1122334455667788u64.to_le_bytes().to_vec();
        expect.extend_from_slice(&7i64.to_le_bytes());
        assert_eq!(
            r.reply_to,
            ReplyTo::Cyclone {
                header: expect.try_into().unwrap()
            }
        );
    }
}
