//! ROS 2's node discovery: `ros_discovery_info`, the topic on which every participant of a
//! DDS-based rmw announces which ROS 2 nodes it holds and which readers and writers belong to
//! each (`rmw_dds_common/msg/ParticipantEntitiesInfo`). `ros2 node list` and `ros2 node info`
//! read only this topic (DDS discovery alone gives topics, not nodes).
//!
//! The message changed between releases. Its `Gid` is
//!
//! - Humble (and Foxy, Galactic): `char[24] data` (the 16-byte DDS GUID, then 8 zero bytes);
//! - Iron, Jazzy, Kilted, Rolling: `uint8[16] data`.
//!
//! The type name is the same in both (`rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_`)
//! and DDS matches the topics by that name, so each side decodes the other's bytes with its
//! own layout: a 24-byte reader sees garbage or a decoding error in a 16-byte sample (the node
//! never shows in `ros2 node list`), and a 16-byte reader sees a participant *without nodes*
//! in a 24-byte sample (the 4 bytes after the GUID are the zero padding, read as the node
//! count). One participant must therefore announce itself in exactly one layout, the one its
//! peers use.
//!
//! rollbase chooses the layout at run time ([`GidLayout`], [`choose_layout`]): the
//! `--ros2-distro` option, else `ROS_DISTRO` when a ROS 2 environment is sourced, else the
//! layout of the first peer announcement it receives ([`detect_layout`]: the sample decodes
//! to its last byte in one layout and not in the other); until it knows, it announces nothing
//! (a ROS 2 peer always announces itself, so the wait ends when one appears). The codec here
//! is pure (bytes in, values out); `node.rs` reads and writes the topic.

use std::fmt;

/// The DDS topic name (no `rt/` prefix: it is not a ROS topic).
pub const TOPIC: &str = "ros_discovery_info";
/// The DDS type name (the same in every release).
pub const TYPE_NAME: &str = "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_";

/// The `Gid` layout of `ros_discovery_info`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GidLayout {
    /// 24 bytes: Humble and older.
    Gid24,
    /// 16 bytes: Iron and newer (Jazzy, Kilted, Rolling).
    Gid16,
}

impl GidLayout {
    /// Bytes of one `Gid`.
    pub fn bytes(self) -> usize {
        match self {
            Self::Gid24 => 24,
            Self::Gid16 => 16,
        }
    }

    /// The releases that use it (for messages).
    pub fn releases(self) -> &'static str {
        match self {
            Self::Gid24 => "Humble and older",
            Self::Gid16 => "Iron, Jazzy and newer",
        }
    }
}

impl fmt::Display for GidLayout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-byte gid ({})", self.bytes(), self.releases())
    }
}

/// Which ROS 2 release's discovery layout to announce (`--ros2-distro`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DistroChoice {
    /// `ROS_DISTRO` if set to a known release, else the peers' layout (detected).
    #[default]
    Auto,
    /// This layout, whatever the environment and the peers say.
    Fixed(GidLayout),
}

/// The layout of a ROS 2 release name (`humble`, `jazzy`, …), `None` for an unknown name.
pub fn layout_of_release(name: &str) -> Option<GidLayout> {
    match name.trim().to_ascii_lowercase().as_str() {
        "foxy" | "galactic" | "humble" => Some(GidLayout::Gid24),
        "iron" | "jazzy" | "kilted" | "lyrical" | "rolling" => Some(GidLayout::Gid16),
        _ => None,
    }
}

impl std::str::FromStr for DistroChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Self::Auto);
        }
        layout_of_release(s).map(Self::Fixed).ok_or_else(|| {
            format!("{s:?}: give auto, or a ROS 2 release: humble, iron, jazzy, kilted or rolling")
        })
    }
}

/// The layout to announce at start-up: the option, else `ros_distro` (the `ROS_DISTRO`
/// environment value); `None`: wait for a peer's announcement. The second value is a warning
/// for an unknown `ROS_DISTRO`.
pub fn choose_layout(
    choice: DistroChoice,
    ros_distro: Option<&str>,
) -> (Option<GidLayout>, Option<String>) {
    match choice {
        DistroChoice::Fixed(l) => (Some(l), None),
        DistroChoice::Auto => match ros_distro.map(str::trim).filter(|s| !s.is_empty()) {
            None => (None, None),
            Some(d) => match layout_of_release(d) {
                Some(l) => (Some(l), None),
                None => (
                    None,
                    Some(format!(
                        "ROS_DISTRO={d:?} is not a ROS 2 release rollbase knows: the discovery layout is taken from the first ROS 2 peer (or give --ros2-distro)"
                    )),
                ),
            },
        },
    }
}

/// One ROS 2 node of a participant.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeEntities {
    /// Namespace (`/`, `/robot1`).
    pub namespace: String,
    /// Node name.
    pub name: String,
    /// GUIDs of its DDS readers (subscriptions, service request readers).
    pub readers: Vec<[u8; 16]>,
    /// GUIDs of its DDS writers (publishers, service reply writers).
    pub writers: Vec<[u8; 16]>,
}

/// `rmw_dds_common/msg/ParticipantEntitiesInfo`: a participant and its nodes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParticipantEntities {
    /// The participant's GUID.
    pub gid: [u8; 16],
    /// Its nodes.
    pub nodes: Vec<NodeEntities>,
}

/// CDR writer (little endian, alignment counted from the start of the payload).
struct W(Vec<u8>);

impl W {
    fn align(&mut self, n: usize) {
        while !self.0.len().is_multiple_of(n) {
            self.0.push(0);
        }
    }
    fn u32(&mut self, v: u32) {
        self.align(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn gid(&mut self, g: &[u8; 16], layout: GidLayout) {
        self.0.extend_from_slice(g);
        self.0.resize(self.0.len() + layout.bytes() - 16, 0);
    }
    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.0.extend_from_slice(s.as_bytes());
        self.0.push(0);
    }
}

/// Encodes the announcement in `layout`: the CDR payload (little endian), without the 4-byte
/// encapsulation header.
pub fn encode(p: &ParticipantEntities, layout: GidLayout) -> Vec<u8> {
    let mut w = W(Vec::with_capacity(128));
    w.gid(&p.gid, layout);
    w.u32(p.nodes.len() as u32);
    for n in &p.nodes {
        w.string(&n.namespace);
        w.string(&n.name);
        for list in [&n.readers, &n.writers] {
            w.u32(list.len() as u32);
            for g in list {
                w.gid(g, layout);
            }
        }
    }
    w.0
}

/// CDR reader over a payload; every read checks the length.
struct R<'a> {
    b: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl R<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8], String> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.b.len());
        match end {
            Some(end) => {
                let s = &self.b[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(format!(
                "{what}: needs {n} bytes at offset {}, the payload has {}",
                self.pos,
                self.b.len()
            )),
        }
    }
    fn u32(&mut self, what: &str) -> Result<u32, String> {
        self.pos = self.pos.div_ceil(4) * 4;
        let s = self.take(4, what)?;
        let a = [s[0], s[1], s[2], s[3]];
        Ok(if self.big_endian {
            u32::from_be_bytes(a)
        } else {
            u32::from_le_bytes(a)
        })
    }
    fn gid(&mut self, layout: GidLayout, what: &str) -> Result<[u8; 16], String> {
        let s = self.take(layout.bytes(), what)?;
        let mut g = [0u8; 16];
        g.copy_from_slice(&s[..16]);
        Ok(g)
    }
    /// A sequence length, checked against the bytes left (each element takes at least `min`).
    fn count(&mut self, min: usize, what: &str) -> Result<usize, String> {
        let n = self.u32(what)? as usize;
        let left = self.b.len() - self.pos;
        if n.saturating_mul(min) > left {
            return Err(format!(
                "{what}: {n} elements cannot fit in the {left} bytes left"
            ));
        }
        Ok(n)
    }
    fn string(&mut self, what: &str) -> Result<String, String> {
        let n = self.u32(what)? as usize;
        if n == 0 {
            return Err(format!("{what}: a CDR string has at least its NUL byte"));
        }
        let s = self.take(n, what)?;
        if s[n - 1] != 0 {
            return Err(format!("{what}: not NUL-terminated"));
        }
        String::from_utf8(s[..n - 1].to_vec()).map_err(|_| format!("{what}: not UTF-8"))
    }
}

/// Decodes an announcement in `layout` from its CDR payload (without the encapsulation
/// header); returns it and the number of bytes it took.
pub fn decode(
    payload: &[u8],
    big_endian: bool,
    layout: GidLayout,
) -> Result<(ParticipantEntities, usize), String> {
    let mut r = R {
        b: payload,
        pos: 0,
        big_endian,
    };
    let gid = r.gid(layout, "participant gid")?;
    // A node takes at least 2 strings (5 bytes each) and 2 sequence lengths.
    let n = r.count(18, "node_entities_info_seq")?;
    let mut nodes = Vec::with_capacity(n);
    for _ in 0..n {
        let namespace = r.string("node_namespace")?;
        let name = r.string("node_name")?;
        let mut lists = [Vec::new(), Vec::new()];
        for (list, what) in lists.iter_mut().zip(["reader_gid_seq", "writer_gid_seq"]) {
            let k = r.count(layout.bytes(), what)?;
            for _ in 0..k {
                list.push(r.gid(layout, what)?);
            }
        }
        let [readers, writers] = lists;
        nodes.push(NodeEntities {
            namespace,
            name,
            readers,
            writers,
        });
    }
    Ok((ParticipantEntities { gid, nodes }, r.pos))
}

/// Decodes `payload` in `layout` only if it takes every byte (up to 3 bytes of end padding).
pub fn decode_exact(
    payload: &[u8],
    big_endian: bool,
    layout: GidLayout,
) -> Result<ParticipantEntities, String> {
    let (p, used) = decode(payload, big_endian, layout)?;
    let left = payload.len() - used;
    if left > 3 {
        return Err(format!(
            "{left} bytes left after the message in the {layout} layout"
        ));
    }
    Ok(p)
}

/// The layout a peer's announcement is in: the one in which it decodes exactly; `None` when
/// it decodes in neither (not an announcement) or in both (ambiguous; the next one decides).
pub fn detect_layout(payload: &[u8], big_endian: bool) -> Option<(GidLayout, ParticipantEntities)> {
    let a = decode_exact(payload, big_endian, GidLayout::Gid24);
    let b = decode_exact(payload, big_endian, GidLayout::Gid16);
    match (a, b) {
        (Ok(p), Err(_)) => Some((GidLayout::Gid24, p)),
        (Err(_), Ok(p)) => Some((GidLayout::Gid16, p)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guid(k: u8) -> [u8; 16] {
        let mut g = [0u8; 16];
        for (i, b) in g.iter_mut().enumerate() {
            *b = k.wrapping_mul(17).wrapping_add(i as u8);
        }
        g
    }

    fn sample() -> ParticipantEntities {
        ParticipantEntities {
            gid: guid(1),
            nodes: vec![NodeEntities {
                namespace: "/robot1".into(),
                name: "rollbase".into(),
                readers: vec![guid(2), guid(3)],
                writers: vec![guid(4)],
            }],
        }
    }

    /// The bytes of both layouts, written out by hand from the .msg definitions of Humble
    /// (char[24]) and Jazzy (uint8[16]).
    #[test]
    fn both_layouts_have_the_documented_bytes() {
        let p = ParticipantEntities {
            gid: guid(1),
            nodes: vec![NodeEntities {
                namespace: "/".into(),
                name: "rb".into(),
                readers: vec![guid(2)],
                writers: vec![],
            }],
        };
        let mut jazzy = guid(1).to_vec();
        jazzy.extend_from_slice(&1u32.to_le_bytes()); // one node
        jazzy.extend_from_slice(&2u32.to_le_bytes()); // "/\0"
        jazzy.extend_from_slice(b"/\0");
        jazzy.extend_from_slice(&[0, 0]); // align
        jazzy.extend_from_slice(&3u32.to_le_bytes()); // "rb\0"
        jazzy.extend_from_slice(b"rb\0");
        jazzy.push(0); // align
        jazzy.extend_from_slice(&1u32.to_le_bytes()); // one reader
        jazzy.extend_from_slice(&guid(2));
        jazzy.extend_from_slice(&0u32.to_le_bytes()); // no writers
        assert_eq!(encode(&p, GidLayout::Gid16), jazzy);

        let mut humble = guid(1).to_vec();
        humble.extend_from_slice(&[0; 8]);
        humble.extend_from_slice(&1u32.to_le_bytes());
        humble.extend_from_slice(&2u32.to_le_bytes());
        humble.extend_from_slice(b"/\0\0\0");
        humble.extend_from_slice(&3u32.to_le_bytes());
        humble.extend_from_slice(b"rb\0\0");
        humble.extend_from_slice(&1u32.to_le_bytes());
        humble.extend_from_slice(&guid(2));
        humble.extend_from_slice(&[0; 8]);
        humble.extend_from_slice(&0u32.to_le_bytes());
        assert_eq!(encode(&p, GidLayout::Gid24), humble);
    }

    #[test]
    fn each_layout_decodes_its_own_bytes_and_is_detected() {
        for layout in [GidLayout::Gid24, GidLayout::Gid16] {
            let bytes = encode(&sample(), layout);
            assert_eq!(decode_exact(&bytes, false, layout).unwrap(), sample());
            let (l, p) = detect_layout(&bytes, false).expect("detected");
            assert_eq!((l, p), (layout, sample()));
            // With end padding, as some writers send it.
            let mut padded = bytes.clone();
            padded.extend_from_slice(&[0, 0, 0]);
            assert_eq!(detect_layout(&padded, false).unwrap().0, layout);
        }
        // An empty participant (no nodes yet) is also told apart: 20 or 28 bytes.
        let empty = ParticipantEntities {
            gid: guid(9),
            nodes: vec![],
        };
        for layout in [GidLayout::Gid24, GidLayout::Gid16] {
            let b = encode(&empty, layout);
            assert_eq!(b.len(), layout.bytes() + 4);
            assert_eq!(detect_layout(&b, false).unwrap(), (layout, empty.clone()));
        }
    }

    /// What goes wrong when the layouts are mixed, the reason rollbase announces only one: a
    /// 16-byte reader sees a 24-byte announcement as a participant without nodes, and a
    /// 24-byte reader cannot decode a 16-byte one.
    #[test]
    fn a_reader_of_the_other_layout_misreads() {
        let humble = encode(&sample(), GidLayout::Gid24);
        let (p, _) = decode(&humble, false, GidLayout::Gid16).unwrap();
        assert_eq!(p.gid, sample().gid);
        assert!(p.nodes.is_empty(), "the zero padding reads as 0 nodes");
        assert!(decode_exact(&humble, false, GidLayout::Gid16).is_err());
        let jazzy = encode(&sample(), GidLayout::Gid16);
        assert!(decode_exact(&jazzy, false, GidLayout::Gid24).is_err());
    }

    #[test]
    fn big_endian_and_garbage() {
        // A big-endian sample: lengths swapped.
        let le = encode(&sample(), GidLayout::Gid16);
        let mut be = le.clone();
        for off in [16usize, 20, 32, 48, 84] {
            be[off..off + 4].reverse();
        }
        assert_eq!(decode_exact(&be, true, GidLayout::Gid16).unwrap(), sample());
        for bad in [&[][..], &[1, 2, 3][..], &[0xff; 40][..]] {
            assert!(detect_layout(bad, false).is_none());
        }
        // A huge sequence length is refused before anything is allocated.
        let mut huge = guid(1).to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = decode(&huge, false, GidLayout::Gid16).unwrap_err();
        assert!(e.contains("cannot fit"), "{e}");
    }

    #[test]
    fn release_names_and_the_choice() {
        assert_eq!(layout_of_release("humble"), Some(GidLayout::Gid24));
        assert_eq!(layout_of_release("Jazzy"), Some(GidLayout::Gid16));
        assert_eq!(layout_of_release("rolling"), Some(GidLayout::Gid16));
        assert_eq!(layout_of_release("melodic"), None);
        assert_eq!("auto".parse::<DistroChoice>(), Ok(DistroChoice::Auto));
        assert!("ardent".parse::<DistroChoice>().is_err());
        let fixed = DistroChoice::Fixed(GidLayout::Gid24);
        assert_eq!(
            choose_layout(fixed, Some("jazzy")),
            (Some(GidLayout::Gid24), None)
        );
        assert_eq!(
            choose_layout(DistroChoice::Auto, Some("humble")),
            (Some(GidLayout::Gid24), None)
        );
        assert_eq!(choose_layout(DistroChoice::Auto, None), (None, None));
        assert_eq!(choose_layout(DistroChoice::Auto, Some(" ")), (None, None));
        let (l, w) = choose_layout(DistroChoice::Auto, Some("noetic"));
        assert!(l.is_none() && w.unwrap().contains("noetic"));
    }
}
