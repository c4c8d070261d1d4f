//! The thin DDS layer under the node: a `rustdds` participant with ROS 2's names, type names
//! and QoS, typed writers for the messages of [`super::msg`], and readers that hand over the
//! raw payload with the sample's RTPS metadata (writer GUID, sequence number, inline
//! `related_sample_identity`).
//!
//! Why rustdds directly and not `ros2-client` (which rollbase used up to issue 26): its
//! service server fixes the request/reply mapping when it is created (one process could not
//! serve rmw_cyclonedds and rmw_fastrtps callers), its `ros_discovery_info` layout is fixed
//! when it is compiled (a `jazzy` build is invisible to Humble's `ros2 node list`), and its
//! subscriptions drop an undecodable sample with a log line of the library's, not a count of
//! ours. Everything ros2-client added over rustdds for rollbase is here in about 200 lines:
//! name mangling (`rt/`, `rq/…Request`, `rr/…Reply`), type names (`pkg::msg::dds_::Type_`),
//! QoS profiles, and the node's announcement ([`super::discovery`]).

use super::msg::{self, RosMsg};
use super::Ros2Error;
use rustdds::no_key::{self, DataWriter, SimpleDataReader};
use rustdds::policy::{Durability, History, Reliability, ResourceLimits};
use rustdds::{
    CDRSerializerAdapter, DomainParticipant, DomainParticipantBuilder, QosPolicies,
    QosPolicyBuilder, RTPSEntity, RepresentationIdentifier, Topic, TopicKind, GUID,
};
use std::marker::PhantomData;
use std::net::IpAddr;

pub use rustdds;

/// QoS profiles.
pub mod qos {
    use super::*;

    /// How long a reliable write may wait for room in a full history.
    fn blocking() -> rustdds::Duration {
        rustdds::Duration::from_millis(100)
    }

    /// ROS 2's default for topics and services (`rmw_qos_profile_default`,
    /// `rmw_qos_profile_services_default`): reliable, volatile, keep last 10.
    pub fn ros_default() -> QosPolicies {
        QosPolicyBuilder::new()
            .reliability(Reliability::Reliable {
                max_blocking_time: blocking(),
            })
            .durability(Durability::Volatile)
            .history(History::KeepLast { depth: 10 })
            .build()
    }

    /// A reader that takes every publisher: best effort matches reliable and best-effort
    /// writers (a reliable reader matches only reliable ones); volatile matches volatile and
    /// transient-local writers. Keep last 10, and rustdds's topic cache bounded to those 10
    /// samples (its default keeps 64): with samples of at most [`super::MAX_SAMPLE_BYTES`],
    /// the cache holds at most 2.5 MiB whatever a publisher sends.
    pub fn any_publisher() -> QosPolicies {
        QosPolicyBuilder::new()
            .reliability(Reliability::BestEffort)
            .durability(Durability::Volatile)
            .history(History::KeepLast { depth: 10 })
            .resource_limits(ResourceLimits {
                max_samples: 10,
                max_instances: 1,
                max_samples_per_instance: 10,
            })
            .build()
    }

    /// Leg commands: as `cmd_vel` ([`any_publisher`]), best effort, so that reliable and
    /// best-effort publishers both match. Up to issue 26 this reader was reliable, because
    /// rustdds 0.15.1 kept the reassembly buffer of a best-effort sample that lost a fragment
    /// (allocated at the announced size at the first fragment) for good (issue 27, finding 8:
    /// three 32 MB leg commands left 94 MB behind). The vendored rustdds
    /// (vendor/rustdds/PATCHES.md) drops samples announcing more than
    /// [`super::MAX_SAMPLE_BYTES`] before allocating, bounds and expires partial
    /// reassemblies, and forgets a vanished writer's: a best-effort reader is bounded too.
    pub fn leg_commands() -> QosPolicies {
        any_publisher()
    }

    /// Latched: reliable, transient local, keep last 1 (`robot_description` as
    /// robot_state_publisher offers it, and `ros_discovery_info` as rmw_dds_common does).
    pub fn latched() -> QosPolicies {
        QosPolicyBuilder::new()
            .reliability(Reliability::Reliable {
                max_blocking_time: blocking(),
            })
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 1 })
            .build()
    }
}

/// The largest sample the vendored rustdds reassembles from fragments
/// (`MAX_FRAGMENTED_SAMPLE_SIZE` in vendor/rustdds/src/rtps/fragment_assembler.rs; the same
/// value): a larger one is dropped before anything is allocated and reported to its reader as
/// `SampleLost`. A leg command for every wheel is under 1 KiB, a Twist 48 bytes; the largest
/// samples a ROS 2 peer sends the node are `ros_discovery_info` announcements (about 0.8 KiB
/// per node of the peer's process: 256 KiB is about 300 nodes in one process).
pub const MAX_SAMPLE_BYTES: usize = 256 * 1024;

/// The DDS topic of a ROS topic (`/odom` → `rt/odom`).
pub fn topic_dds_name(absolute: &str) -> String {
    format!("rt{absolute}")
}

/// The DDS topics of a ROS service (`/rollbase/stop` → `rq/rollbase/stopRequest`,
/// `rr/rollbase/stopReply`).
pub fn service_dds_names(absolute: &str) -> (String, String) {
    (format!("rq{absolute}Request"), format!("rr{absolute}Reply"))
}

/// A received sample: the payload after the encapsulation header, and its metadata.
#[derive(Clone, Debug)]
pub struct RawSample {
    /// Big-endian CDR (else little endian).
    pub big_endian: bool,
    /// The CDR payload.
    pub payload: Vec<u8>,
}

/// Metadata of a received sample.
#[derive(Clone, Copy, Debug)]
pub struct SampleMeta {
    /// The writer's GUID.
    pub writer_guid: [u8; 16],
    /// RTPS sequence number.
    pub sequence_number: i64,
    /// Inline `related_sample_identity` (writer GUID, sequence number), if sent.
    pub related: Option<([u8; 16], i64)>,
}

/// The deserializer adapter that keeps the bytes (plain CDR, either endianness; other
/// representations are refused by rustdds and reach the reader as an error naming them).
pub struct RawAdapter;

const PLAIN_CDR: [RepresentationIdentifier; 2] = [
    RepresentationIdentifier::CDR_LE,
    RepresentationIdentifier::CDR_BE,
];

impl no_key::DeserializerAdapter<RawSample> for RawAdapter {
    type Error = std::convert::Infallible;
    type Decoded = RawSample;
    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &PLAIN_CDR
    }
    fn transform_decoded(decoded: RawSample) -> RawSample {
        decoded
    }
}

/// The decoder of [`RawAdapter`].
#[derive(Clone)]
pub struct RawDecoder;

impl<'de> no_key::Decode<'de, RawSample> for RawDecoder {
    type Error = std::convert::Infallible;
    fn decode_bytes(
        self,
        input_bytes: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawSample, Self::Error> {
        Ok(RawSample {
            big_endian: encoding == RepresentationIdentifier::CDR_BE,
            payload: input_bytes.to_vec(),
        })
    }
}

impl no_key::DefaultDecoder<RawSample> for RawAdapter {
    type Decoder = RawDecoder;
    const DECODER: Self::Decoder = RawDecoder;
}

/// A payload written as it is (little-endian CDR, without the encapsulation header).
#[derive(Debug)]
pub struct RawPayload(pub Vec<u8>);

/// The serializer adapter of [`RawPayload`].
pub struct RawWriterAdapter;

impl no_key::SerializerAdapter<RawPayload> for RawWriterAdapter {
    type Error = std::convert::Infallible;
    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }
    fn to_bytes(value: &RawPayload) -> Result<rustdds::bytes::Bytes, Self::Error> {
        Ok(rustdds::bytes::Bytes::copy_from_slice(&value.0))
    }
}

/// A reader of raw samples.
pub type RawReader = SimpleDataReader<RawSample, RawAdapter>;
/// A writer of raw payloads.
pub type RawWriter = DataWriter<RawPayload, RawWriterAdapter>;
/// A writer of a ROS message type.
pub type MsgWriter<T> = DataWriter<T, CDRSerializerAdapter<T>>;

/// The metadata of a sample taken from a [`RawReader`].
pub fn sample_meta(dcc: &no_key::DeserializedCacheChange<RawSample>) -> SampleMeta {
    SampleMeta {
        writer_guid: dcc.writer_guid().to_bytes(),
        sequence_number: i64::from(dcc.sequence_number),
        related: dcc
            .related_sample_identity()
            .map(|s| (s.writer_guid.to_bytes(), i64::from(s.sequence_number))),
    }
}

/// A DDS participant with one publisher and one subscriber, creating ROS 2 endpoints.
pub struct Dds {
    participant: DomainParticipant,
    publisher: rustdds::Publisher,
    subscriber: rustdds::Subscriber,
}

fn entity_err(
    what: &'static str,
    name: &str,
) -> impl FnOnce(rustdds::dds::CreateError) -> Ros2Error {
    let name = name.to_string();
    move |e| Ros2Error::Entity {
        what,
        name,
        message: format!("{e:?}"),
    }
}

impl Dds {
    /// Joins `domain`; with `only` non-empty, announces only on the interfaces with those
    /// addresses.
    pub fn new(domain: u16, only: &[IpAddr]) -> Result<Self, Ros2Error> {
        let mut b = DomainParticipantBuilder::new(domain);
        if !only.is_empty() {
            b = b.with_only_networks(only.iter().copied());
        }
        let perr = |e: rustdds::dds::CreateError| Ros2Error::Participant {
            domain,
            message: format!("{e:?}"),
        };
        let participant = b.build().map_err(perr)?;
        let publisher = participant
            .create_publisher(&qos::ros_default())
            .map_err(perr)?;
        let subscriber = participant
            .create_subscriber(&qos::ros_default())
            .map_err(perr)?;
        Ok(Self {
            participant,
            publisher,
            subscriber,
        })
    }

    /// The participant.
    pub fn participant(&self) -> &DomainParticipant {
        &self.participant
    }

    /// The participant's GUID.
    pub fn guid(&self) -> GUID {
        self.participant.guid()
    }

    /// A DDS topic.
    pub fn topic(
        &self,
        dds_name: &str,
        type_name: &str,
        q: &QosPolicies,
    ) -> Result<Topic, Ros2Error> {
        self.participant
            .create_topic(dds_name.into(), type_name.into(), q, TopicKind::NoKey)
            .map_err(entity_err("topic", dds_name))
    }

    /// A writer of `T` on the ROS topic `absolute` (e.g. `/odom`).
    pub fn writer<T: RosMsg>(
        &self,
        absolute: &str,
        q: QosPolicies,
    ) -> Result<MsgWriter<T>, Ros2Error> {
        let t = self.topic(&topic_dds_name(absolute), &T::DEF.dds_type_name(), &q)?;
        self.publisher
            .create_datawriter_no_key::<T, CDRSerializerAdapter<T>>(&t, Some(q))
            .map_err(entity_err("publisher", absolute))
    }

    /// A raw writer on a DDS topic.
    pub fn raw_writer(
        &self,
        dds_name: &str,
        type_name: &str,
        q: QosPolicies,
    ) -> Result<RawWriter, Ros2Error> {
        let t = self.topic(dds_name, type_name, &q)?;
        self.publisher
            .create_datawriter_no_key::<RawPayload, RawWriterAdapter>(&t, Some(q))
            .map_err(entity_err("writer", dds_name))
    }

    /// A raw reader on a DDS topic.
    pub fn raw_reader(
        &self,
        dds_name: &str,
        type_name: &str,
        q: QosPolicies,
    ) -> Result<RawReader, Ros2Error> {
        let t = self.topic(dds_name, type_name, &q)?;
        self.subscriber
            .create_simple_datareader_no_key::<RawSample, RawAdapter>(&t, Some(q))
            .map_err(entity_err("reader", dds_name))
    }

    /// A reader of `T` on the ROS topic `absolute`.
    pub fn reader<T: RosMsg>(
        &self,
        absolute: &str,
        q: QosPolicies,
    ) -> Result<MsgReader<T>, Ros2Error> {
        Ok(MsgReader {
            raw: self.raw_reader(&topic_dds_name(absolute), &T::DEF.dds_type_name(), q)?,
            ty: PhantomData,
        })
    }
}

/// Decodes a raw sample as `T` (trailing padding accepted).
pub fn decode<T: RosMsg>(s: &RawSample) -> Result<T, String> {
    msg::from_cdr_payload::<T>(&s.payload, s.big_endian)
        .map(|(v, _)| v)
        .map_err(|e| e.to_string())
}

/// A reader of a ROS message type (for peers in tests and tools; the node reads raw).
pub struct MsgReader<T> {
    raw: RawReader,
    ty: PhantomData<T>,
}

impl<T: RosMsg> MsgReader<T> {
    /// The next sample, if one arrived: `Err` says why it did not decode.
    pub fn take(&self) -> Result<Option<T>, String> {
        self.raw.drain_read_notifications();
        match self.raw.try_take_one() {
            Ok(Some(dcc)) => decode::<T>(&dcc.into_value()).map(Some),
            Ok(None) => Ok(None),
            Err(e) => Err(e.to_string()),
        }
    }

    /// The DDS reader's GUID.
    pub fn guid(&self) -> GUID {
        self.raw.guid()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_names_on_dds() {
        assert_eq!(topic_dds_name("/robot1/odom"), "rt/robot1/odom");
        assert_eq!(
            service_dds_names("/rollbase/stop"),
            (
                "rq/rollbase/stopRequest".to_string(),
                "rr/rollbase/stopReply".to_string()
            )
        );
    }

    #[test]
    fn a_best_effort_reader_matches_reliable_and_best_effort_writers() {
        // rustdds' own QoS check (offered.compliance_failure_wrt(requested)), the one that
        // decides matching: a reliable reader refuses a best-effort writer, ours does not.
        let be_writer = QosPolicyBuilder::new()
            .reliability(Reliability::BestEffort)
            .build();
        let rel_writer = qos::ros_default();
        let reader = qos::any_publisher();
        assert_eq!(be_writer.compliance_failure_wrt(&reader), None);
        assert_eq!(rel_writer.compliance_failure_wrt(&reader), None);
        assert_eq!(
            be_writer.compliance_failure_wrt(&qos::ros_default()),
            Some(rustdds::dds::qos::QosPolicyId::Reliability)
        );
        // A transient-local writer (a latched publisher) matches the volatile reader too.
        assert_eq!(qos::latched().compliance_failure_wrt(&reader), None);
    }

    #[test]
    fn the_leg_reader_takes_every_publisher_with_a_cache_of_its_depth() {
        // Best effort (issue 26: best-effort leg publishers move the legs too): reliable,
        // best-effort and latched writers all match.
        let legs = qos::leg_commands();
        assert_eq!(legs.reliability(), Some(Reliability::BestEffort));
        assert_eq!(qos::ros_default().compliance_failure_wrt(&legs), None);
        assert_eq!(qos::latched().compliance_failure_wrt(&legs), None);
        let be_writer = QosPolicyBuilder::new()
            .reliability(Reliability::BestEffort)
            .build();
        assert_eq!(be_writer.compliance_failure_wrt(&legs), None);
        // rustdds's topic cache keeps max(max_samples, depth) samples (64 by default): both
        // command readers keep 10.
        for q in [legs, qos::any_publisher()] {
            assert_eq!(q.history(), Some(History::KeepLast { depth: 10 }));
            assert_eq!(q.resource_limits().map(|r| r.max_samples), Some(10));
        }
    }
}
