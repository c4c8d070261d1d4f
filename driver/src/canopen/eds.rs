//! Device description files (CiA 306 EDS, and DCF: an EDS with the values one device is
//! configured to): parsed, and the boot plan checked against them before any frame is sent.
//!
//! # What is read (CiA 306 v1.3)
//!
//! An EDS is INI text: `[Section]` headers, `Key=Value` lines, `;` comments; section and key
//! names are case-insensitive. `[DeviceInfo]` names the device (`VendorName`, `ProductName`)
//! and its PDO counts (`NrOfRXPDO`, `NrOfTXPDO`). `[MandatoryObjects]`, `[OptionalObjects]`
//! and `[ManufacturerObjects]` list the objects the device has (`SupportedObjects=n`, then
//! `1=0x1000` …). Each object is a section named by its index in hex (`[6060]`), each
//! sub-index of an ARRAY or RECORD one named `[1018sub1]` (sub-index in hex); an ARRAY may
//! instead give `CompactSubObj=n` (sub-indices 1..n alike, sub-index 0 their count). The keys
//! used: `ObjectType` (0x7 VAR, 0x8 ARRAY, 0x9 RECORD), `DataType` (CiA 301 codes: 0x0002
//! INTEGER8 … 0x0007 UNSIGNED32, 0x0009 VISIBLE_STRING …), `AccessType` (`ro`, `wo`, `rw`,
//! `rwr`, `rww`, `const`), `LowLimit`, `HighLimit`, `DefaultValue`, `PDOMapping` (0/1) and, in
//! a DCF, `ParameterValue`. Numbers are decimal, `0x` hexadecimal or (leading `0`) octal, and
//! may add `$NODEID` (`$NODEID+0x180`): it is resolved with the node the file is checked for.
//!
//! # The check ([`check_plan`])
//!
//! For every step of a device's boot plan (see [`super::config`]): the object exists (an
//! optional step's object may be missing: the boot skips it), a written object is writable
//! (`rw`, `wo`, `rwr`, `rww`), a read one readable, the value's size is the data type's, the
//! value lies within `LowLimit`..=`HighLimit`; every object the plan maps into a PDO has
//! `PDOMapping=1` and the entry's length is its data type's; the number of mapped objects
//! fits the mapping object (its sub-indices), and 64 bits. A read the plan compares (encoder
//! resolution, measuring step …) against a DCF's `ParameterValue` is compared ahead. Each
//! error names the device (node, role, wheel), the object as 0xIIII:SS, the file and what to
//! do.
//!
//! # DCF values ([`dcf_writes`])
//!
//! A DCF's `ParameterValue`s are written as extra SDO steps, after the plan's own
//! configuration and before the platform file's `[[cia402.sdo]]` list (so the platform file
//! has the last word), in index order: a DCF's value replaces a default of the plan (its
//! optional steps: quick stop option 0x605A and deceleration 0x6085, …). Not written: objects
//! that are not writable (`ro`, `const`), objects the plan needs written as it writes them
//! (its mandatory steps: PDOs, heartbeat, mode of operation …), the PDO
//! parameters 0x1400–0x1BFF (the plan owns the PDOs), store/restore 0x1010/0x1011 (a value
//! there saves to or wipes the device's memory), and values that are not 1–4 bytes long
//! (strings, domains: the boot plan's transfers are expedited).

use super::config::{for_node, Cia402Config, Role, SdoOp};
use super::od;
use super::pdo::MapEntry;
use super::sdo::SdoData;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Sections by lower-case name: (header line, keys by lower-case name: (value, line)).
type Sections = BTreeMap<String, (usize, BTreeMap<String, (String, usize)>)>;

/// A DCF value not written: ((index, sub), why).
pub type DcfSkipped = ((u16, u8), DcfSkip);

/// What a line of a description file, or the boot plan checked against it, got wrong.
#[derive(Debug, thiserror::Error)]
pub enum EdsError {
    /// The file could not be read.
    #[error(transparent)]
    Input(#[from] crate::input::InputError),
    /// The file is not a description file this reader understands.
    #[error("{path}:{line}: {reason}; check the file (CiA 306 EDS/DCF) or ask its vendor for a valid one")]
    Parse {
        /// The file.
        path: String,
        /// Line number (1-based; 0: the file as a whole).
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// The boot plan does something the device's description says it cannot take.
    #[error("node {node} ({role} of wheel {wheel}): 0x{index:04X}:{sub:02X} {problem} (device description {path})")]
    Plan {
        /// The file.
        path: String,
        /// Node-ID.
        node: u8,
        /// Role.
        role: Role,
        /// Wheel, 1-based as in messages.
        wheel: usize,
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// What is wrong and what to do.
        problem: PlanProblem,
    },
}

/// How a plan step disagrees with a device description (the message says what to do).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PlanProblem {
    /// The object is not in the description.
    Missing {
        /// The plan writes it (else it reads it).
        write: bool,
        /// The step comes from the platform file's `[[cia402.sdo]]` list.
        extra: bool,
    },
    /// The plan writes an object the description says cannot be written.
    NotWritable {
        /// `ro` or `const`.
        access: &'static str,
        /// The step comes from the platform file's `[[cia402.sdo]]` list.
        extra: bool,
    },
    /// The plan reads a write-only object.
    NotReadable,
    /// The plan's value has another size than the object's data type.
    Size {
        /// Bytes the plan writes.
        plan: usize,
        /// Bytes of the data type.
        object: usize,
        /// The data type code.
        data_type: u16,
    },
    /// The plan's value lies outside `LowLimit..=HighLimit`.
    OutOfRange {
        /// The value written.
        value: i128,
        /// `LowLimit`, when given.
        low: Option<i128>,
        /// `HighLimit`, when given.
        high: Option<i128>,
    },
    /// The plan maps an object that cannot be mapped (`PDOMapping=0`).
    NotMappable {
        /// Which PDO ("TPDO2" …).
        pdo: String,
        /// The mapping object (0x1A01 …).
        map_index: u16,
    },
    /// The plan maps an object with a length other than its data type's.
    MappedLength {
        /// Which PDO.
        pdo: String,
        /// Bits in the mapping entry.
        bits: u8,
        /// Bits of the data type.
        object_bits: u32,
    },
    /// More objects mapped than the mapping object holds, or more than 64 bits.
    Capacity {
        /// Which PDO.
        pdo: String,
        /// Objects mapped.
        entries: u32,
        /// Entries the mapping object has.
        max_entries: u32,
        /// Bits mapped.
        bits: u32,
    },
    /// A DCF configures the device to another value than the one the plan checks for.
    DcfMismatch {
        /// What the object is.
        what: &'static str,
        /// The DCF's ParameterValue (masked as the plan compares it).
        dcf: u32,
        /// What the plan expects.
        expected: u32,
    },
}

impl std::fmt::Display for PlanProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Missing { write, extra } => {
                let op = if *write { "writes" } else { "reads" };
                if *extra {
                    write!(f, "is not in the device's description, but the platform file's [[cia402.sdo]] list {op} it: remove that entry, mark it `optional = true`, or fix the file if the device has the object")
                } else {
                    write!(f, "is not in the device's description, but the boot plan {op} it (the profile needs it): is this the right file for this device (cia402.eds), or is the device not a CiA 402/406 device of the kind configured?")
                }
            }
            Self::NotWritable { access, extra } => {
                if *extra {
                    write!(f, "is `{access}` in the device's description, but the platform file's [[cia402.sdo]] list writes it: remove that entry (the device cannot take it)")
                } else {
                    write!(f, "is `{access}` in the device's description, but the boot plan writes it: the device cannot be configured for this profile as it is (check the file, or the device's firmware)")
                }
            }
            Self::NotReadable => write!(
                f,
                "is write-only in the device's description, but the boot plan reads it to check the platform file against the device"
            ),
            Self::Size {
                plan,
                object,
                data_type,
            } => write!(
                f,
                "is {object} bytes long (data type 0x{data_type:04X}) but the plan writes {plan}: set `size = {object}` for it in [[cia402.sdo]]"
            ),
            Self::OutOfRange { value, low, high } => {
                write!(f, "value {value} (0x{value:X}) is outside the device's range")?;
                match (low, high) {
                    (Some(l), Some(h)) => write!(f, " {l}..={h}")?,
                    (Some(l), None) => write!(f, " (at least {l})")?,
                    (None, Some(h)) => write!(f, " (at most {h})")?,
                    (None, None) => {}
                }
                write!(f, ": change the value in the platform file")
            }
            Self::NotMappable { pdo, map_index } => write!(
                f,
                "cannot be mapped into a PDO (PDOMapping=0), but the plan maps it into {pdo} (0x{map_index:04X}): remove it from cia402.status_extra, or choose an object the device can map"
            ),
            Self::MappedLength {
                pdo,
                bits,
                object_bits,
            } => write!(
                f,
                "is {object_bits} bits long, but the plan maps {bits} bits of it into {pdo}: give the entry's length as the object's (e.g. 0x603F0010 for 16 bits)"
            ),
            Self::Capacity {
                pdo,
                entries,
                max_entries,
                bits,
            } => write!(
                f,
                "{pdo} would hold {entries} objects in {bits} bits, but the device's mapping object holds {max_entries} entries and a PDO 64 bits: map fewer objects (cia402.status_extra)"
            ),
            Self::DcfMismatch {
                what,
                dcf,
                expected,
            } => write!(
                f,
                "{what}: the DCF configures 0x{dcf:X}, the platform file expects 0x{expected:X}: make them agree (the boot would fail on this read)"
            ),
        }
    }
}

/// Access of an object (CiA 306 `AccessType`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Read only.
    Ro,
    /// Write only.
    Wo,
    /// Read and write.
    Rw,
    /// Read and write, mapped into TPDOs.
    Rwr,
    /// Read and write, mapped into RPDOs.
    Rww,
    /// Read only, never changes.
    Const,
}

impl Access {
    fn parse(s: &str) -> Option<Self> {
        Some(match s.trim().to_ascii_lowercase().as_str() {
            "ro" => Self::Ro,
            "wo" => Self::Wo,
            "rw" => Self::Rw,
            "rwr" => Self::Rwr,
            "rww" => Self::Rww,
            "const" => Self::Const,
            _ => return None,
        })
    }

    /// The access as the file spells it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ro => "ro",
            Self::Wo => "wo",
            Self::Rw => "rw",
            Self::Rwr => "rwr",
            Self::Rww => "rww",
            Self::Const => "const",
        }
    }

    /// True when an SDO download is allowed.
    pub fn writable(self) -> bool {
        matches!(self, Self::Wo | Self::Rw | Self::Rwr | Self::Rww)
    }

    /// True when an SDO upload is allowed.
    pub fn readable(self) -> bool {
        self != Self::Wo
    }
}

/// A number of a description file: a constant plus, with `$NODEID`, the node-ID.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Value {
    /// The constant part.
    pub base: i128,
    /// `$NODEID` is added.
    pub plus_node: bool,
}

impl Value {
    /// The value for a device at `node`.
    pub fn at(self, node: u8) -> i128 {
        self.base + if self.plus_node { i128::from(node) } else { 0 }
    }

    /// Parses `0x1A`, `26`, `-3`, `032` (octal), `$NODEID+0x180`, `0x180+$NODEID`.
    pub fn parse(text: &str) -> Option<Self> {
        let t: String = text.chars().filter(|c| !c.is_whitespace()).collect();
        let upper = t.to_ascii_uppercase();
        if let Some(pos) = upper.find("$NODEID") {
            let rest = format!("{}{}", &t[..pos], &t[pos + 7..]);
            let rest = rest.trim_matches('+');
            let base = if rest.is_empty() { 0 } else { number(rest)? };
            return Some(Self {
                base,
                plus_node: true,
            });
        }
        Some(Self {
            base: number(&t)?,
            plus_node: false,
        })
    }
}

fn number(t: &str) -> Option<i128> {
    let (neg, digits) = match t.strip_prefix('-') {
        Some(d) => (true, d),
        None => (false, t.strip_prefix('+').unwrap_or(t)),
    };
    if digits.is_empty() {
        return None;
    }
    let v = if let Some(h) = digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        i128::from_str_radix(h, 16).ok()?
    } else if digits.len() > 1 && digits.starts_with('0') {
        i128::from_str_radix(&digits[1..], 8).ok()?
    } else {
        digits.parse::<i128>().ok()?
    };
    Some(if neg { -v } else { v })
}

/// One object or sub-index of a description.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    /// `ParameterName`.
    pub name: String,
    /// `DataType` (CiA 301 code).
    pub data_type: u16,
    /// `AccessType`.
    pub access: Access,
    /// `LowLimit`.
    pub low: Option<Value>,
    /// `HighLimit`.
    pub high: Option<Value>,
    /// `DefaultValue` (numbers only).
    pub default: Option<Value>,
    /// `PDOMapping=1`.
    pub pdo_mapping: bool,
    /// A DCF's `ParameterValue` (numbers only).
    pub parameter: Option<Value>,
}

/// Size in bytes of a CiA 301 data type, `None` for strings and domains.
pub fn type_size(data_type: u16) -> Option<usize> {
    Some(match data_type {
        0x0001 | 0x0002 | 0x0005 => 1,
        0x0003 | 0x0006 => 2,
        0x0010 | 0x0016 => 3,
        0x0004 | 0x0007 | 0x0008 => 4,
        0x0012 | 0x0018 => 5,
        0x0013 | 0x0019 => 6,
        0x0014 | 0x001A => 7,
        0x0011 | 0x0015 | 0x001B => 8,
        _ => return None,
    })
}

/// True for the signed integer types.
fn type_signed(data_type: u16) -> bool {
    matches!(
        data_type,
        0x0002 | 0x0003 | 0x0004 | 0x0010 | 0x0012 | 0x0013 | 0x0014 | 0x0015
    )
}

/// A parsed EDS or DCF.
#[derive(Clone, Debug, PartialEq)]
pub struct Eds {
    /// Where it was read from (for messages).
    pub path: String,
    /// `[DeviceInfo] VendorName`.
    pub vendor: String,
    /// `[DeviceInfo] ProductName`.
    pub product: String,
    /// `[DeviceInfo] NrOfRXPDO`.
    pub rx_pdos: Option<u32>,
    /// `[DeviceInfo] NrOfTXPDO`.
    pub tx_pdos: Option<u32>,
    /// Some object has a `ParameterValue` (a DCF).
    pub dcf: bool,
    entries: BTreeMap<(u16, u8), Entry>,
    /// Sub-indices per ARRAY/RECORD (`SubNumber`, or `CompactSubObj` + 1).
    sub_number: BTreeMap<u16, u32>,
    indices: BTreeSet<u16>,
}

/// Lines of a description file the parser takes at most (a 8 MiB file of short lines).
const MAX_LINES: usize = 1 << 20;

impl Eds {
    /// Parses the text of a description file read from `path` (for messages).
    pub fn parse(text: &str, path: &str) -> Result<Self, EdsError> {
        let err = |line: usize, reason: String| EdsError::Parse {
            path: path.to_string(),
            line,
            reason,
        };
        // section (upper case) → (key upper case → (value, line)), in file order.
        let mut sections: Sections = BTreeMap::new();
        let mut current: Option<String> = None;
        for (k, raw) in text.lines().enumerate() {
            let line_no = k + 1;
            if k >= MAX_LINES {
                return Err(err(line_no, format!("more than {MAX_LINES} lines")));
            }
            let line = raw.trim();
            if line.is_empty() || line.starts_with(';') || line.starts_with('#') {
                continue;
            }
            if let Some(rest) = line.strip_prefix('[') {
                let Some(name) = rest.strip_suffix(']') else {
                    return Err(err(line_no, format!("section header `{line}` has no `]`")));
                };
                let name = name.trim().to_ascii_uppercase();
                sections
                    .entry(name.clone())
                    .or_insert_with(|| (line_no, BTreeMap::new()));
                current = Some(name);
                continue;
            }
            let Some((key, value)) = line.split_once('=') else {
                return Err(err(
                    line_no,
                    format!("`{line}` is neither a [section] nor a Key=Value line"),
                ));
            };
            let Some(sec) = &current else {
                return Err(err(line_no, format!("`{line}` comes before any [section]")));
            };
            // A value may carry a trailing comment.
            let value = value.split(';').next().unwrap_or("").trim().to_string();
            if let Some((_, keys)) = sections.get_mut(sec) {
                keys.insert(key.trim().to_ascii_uppercase(), (value, line_no));
            }
        }
        let get = |sec: &str, key: &str| -> Option<(String, usize)> {
            sections.get(sec).and_then(|(_, m)| m.get(key)).cloned()
        };
        let num_u32 = |sec: &str, key: &str| -> Result<Option<u32>, EdsError> {
            match get(sec, key) {
                None => Ok(None),
                Some((v, _)) if v.is_empty() => Ok(None),
                Some((v, l)) => match Value::parse(&v) {
                    Some(x) if !x.plus_node && (0..=i128::from(u32::MAX)).contains(&x.base) => {
                        Ok(Some(x.base as u32))
                    }
                    _ => Err(err(l, format!("[{sec}] {key}={v} is not a number"))),
                },
            }
        };
        if !sections.contains_key("DEVICEINFO") {
            return Err(err(
                0,
                "no [DeviceInfo] section: not an EDS or DCF (CiA 306)".into(),
            ));
        }
        let mut indices = BTreeSet::new();
        let mut listed_any = false;
        for list in ["MANDATORYOBJECTS", "OPTIONALOBJECTS", "MANUFACTUREROBJECTS"] {
            let Some((_, keys)) = sections.get(list) else {
                continue;
            };
            listed_any = true;
            let n = num_u32(list, "SUPPORTEDOBJECTS")?.unwrap_or(0);
            for k in 1..=n {
                let Some((v, l)) = keys.get(&k.to_string()).cloned() else {
                    let line = sections.get(list).map_or(0, |s| s.0);
                    return Err(err(
                        line,
                        format!("[{list}] says SupportedObjects={n} but has no entry {k}"),
                    ));
                };
                match Value::parse(&v) {
                    Some(x) if !x.plus_node && (0x1000..=0xFFFF).contains(&x.base) => {
                        indices.insert(x.base as u16);
                    }
                    _ => {
                        return Err(err(
                            l,
                            format!("[{list}] {k}={v} is not an object index 0x1000..=0xFFFF"),
                        ))
                    }
                }
            }
        }
        if !listed_any {
            return Err(err(
                0,
                "no [MandatoryObjects], [OptionalObjects] or [ManufacturerObjects] list: the file does not say which objects the device has".into(),
            ));
        }
        let mut eds = Eds {
            path: path.to_string(),
            vendor: get("DEVICEINFO", "VENDORNAME")
                .map(|v| v.0)
                .unwrap_or_default(),
            product: get("DEVICEINFO", "PRODUCTNAME")
                .map(|v| v.0)
                .unwrap_or_default(),
            rx_pdos: num_u32("DEVICEINFO", "NROFRXPDO")?,
            tx_pdos: num_u32("DEVICEINFO", "NROFTXPDO")?,
            dcf: false,
            entries: BTreeMap::new(),
            sub_number: BTreeMap::new(),
            indices: indices.clone(),
        };
        for &index in &indices {
            let sec = format!("{index:04X}");
            let Some(sec_line) = sections.get(&sec).map(|s| s.0) else {
                return Err(err(
                    0,
                    format!("object 0x{index:04X} is listed but has no [{sec}] section"),
                ));
            };
            let object_type = match get(&sec, "OBJECTTYPE") {
                None => 7,
                Some((v, l)) => match Value::parse(&v) {
                    Some(x) if !x.plus_node => x.base,
                    _ => return Err(err(l, format!("[{sec}] ObjectType={v} is not a number"))),
                },
            };
            match object_type {
                0x7 | 0x2 => {
                    let e = entry(&sections, &sec, sec_line, path)?;
                    eds.insert(index, 0, e);
                }
                0x8 | 0x9 => {
                    if let Some(n) = num_u32(&sec, "COMPACTSUBOBJ")? {
                        if n > 0 {
                            let e = entry(&sections, &sec, sec_line, path)?;
                            eds.insert(
                                index,
                                0,
                                Entry {
                                    name: "number of entries".into(),
                                    data_type: 0x0005,
                                    access: Access::Ro,
                                    low: None,
                                    high: None,
                                    default: Some(Value {
                                        base: i128::from(n),
                                        plus_node: false,
                                    }),
                                    pdo_mapping: false,
                                    parameter: None,
                                },
                            );
                            for s in 1..=n.min(254) {
                                eds.insert(index, s as u8, e.clone());
                            }
                            eds.sub_number.insert(index, n + 1);
                            continue;
                        }
                    }
                    // Sub-index sections [IIIIsubS] (S hex), as many as SubNumber says.
                    let prefix = format!("{sec}SUB");
                    let mut found = 0u32;
                    for (name, (line, _)) in sections.range(prefix.clone()..) {
                        let Some(s) = name.strip_prefix(&prefix) else {
                            break;
                        };
                        let Ok(sub) = u8::from_str_radix(s, 16) else {
                            return Err(err(
                                *line,
                                format!("[{name}]: `{s}` is not a sub-index in hex"),
                            ));
                        };
                        let e = entry(&sections, name, *line, path)?;
                        eds.insert(index, sub, e);
                        found += 1;
                    }
                    let declared = num_u32(&sec, "SUBNUMBER")?.unwrap_or(found);
                    if found == 0 {
                        return Err(err(
                            sec_line,
                            format!("[{sec}] is an ARRAY/RECORD but has no [{sec}subN] sections"),
                        ));
                    }
                    eds.sub_number.insert(index, declared.max(found));
                }
                other => {
                    return Err(err(
                        sec_line,
                        format!("[{sec}] ObjectType=0x{other:X} is not VAR (7), ARRAY (8), RECORD (9) or DOMAIN (2)"),
                    ))
                }
            }
        }
        eds.dcf = eds.entries.values().any(|e| e.parameter.is_some());
        Ok(eds)
    }

    /// Reads and parses a file (bounded: [`crate::input::MAX_EDS_BYTES`]).
    pub fn load(path: &Path) -> Result<Self, EdsError> {
        let text = crate::input::read_text_latin1(
            path,
            crate::input::MAX_EDS_BYTES,
            "device description (EDS/DCF)",
        )?;
        Self::parse(&text, &path.display().to_string())
    }

    fn insert(&mut self, index: u16, sub: u8, e: Entry) {
        self.entries.insert((index, sub), e);
    }

    /// The object or sub-index, when the device has it.
    pub fn get(&self, index: u16, sub: u8) -> Option<&Entry> {
        self.entries.get(&(index, sub))
    }

    /// True when the device has object `index` (any sub-index).
    pub fn has_index(&self, index: u16) -> bool {
        self.indices.contains(&index)
    }

    /// Entries of a mapping object: its sub-indices minus sub-index 0.
    fn mapping_capacity(&self, map_index: u16) -> u32 {
        let subs = self
            .sub_number
            .get(&map_index)
            .copied()
            .unwrap_or(1)
            .saturating_sub(1);
        match self.get(map_index, 0).and_then(|e| e.high) {
            Some(h) => subs.min(h.base.clamp(0, 64) as u32),
            None => subs,
        }
    }

    /// Every entry, in index order.
    pub fn entries(&self) -> impl Iterator<Item = ((u16, u8), &Entry)> {
        self.entries.iter().map(|(k, v)| (*k, v))
    }
}

fn entry(sections: &Sections, sec: &str, sec_line: usize, path: &str) -> Result<Entry, EdsError> {
    let err = |line: usize, reason: String| EdsError::Parse {
        path: path.to_string(),
        line,
        reason,
    };
    let keys = sections.get(sec).map(|s| &s.1);
    let get = |k: &str| keys.and_then(|m| m.get(k)).cloned();
    let data_type = match get("DATATYPE") {
        None => return Err(err(sec_line, format!("[{sec}] has no DataType"))),
        Some((v, l)) => match Value::parse(&v) {
            Some(x) if !x.plus_node && (0..=0xFFFF).contains(&x.base) => x.base as u16,
            _ => return Err(err(l, format!("[{sec}] DataType={v} is not a type code"))),
        },
    };
    let access = match get("ACCESSTYPE") {
        None => return Err(err(sec_line, format!("[{sec}] has no AccessType"))),
        Some((v, l)) => Access::parse(&v).ok_or_else(|| {
            err(
                l,
                format!("[{sec}] AccessType={v} is not ro, wo, rw, rwr, rww or const"),
            )
        })?,
    };
    let numeric = type_size(data_type).is_some();
    let num = |k: &str| -> Result<Option<Value>, EdsError> {
        match get(k) {
            Some((v, l)) if !v.is_empty() && numeric => Value::parse(&v)
                .map(Some)
                .ok_or_else(|| err(l, format!("[{sec}] {k}={v} is not a number"))),
            _ => Ok(None),
        }
    };
    let pdo_mapping = match get("PDOMAPPING") {
        None => false,
        Some((v, l)) => match v.as_str() {
            "0" | "" => false,
            "1" => true,
            _ => return Err(err(l, format!("[{sec}] PDOMapping={v} is not 0 or 1"))),
        },
    };
    Ok(Entry {
        name: get("PARAMETERNAME").map(|v| v.0).unwrap_or_default(),
        data_type,
        access,
        low: num("LOWLIMIT")?,
        high: num("HIGHLIMIT")?,
        default: num("DEFAULTVALUE")?,
        pdo_mapping,
        parameter: num("PARAMETERVALUE")?,
    })
}

/// The value of an SDO write as the object's data type reads it (sign-extended for the
/// signed types).
fn as_typed(data: &SdoData, data_type: u16) -> i128 {
    if type_signed(data_type) {
        i128::from(data.as_i32())
    } else {
        i128::from(data.as_u32())
    }
}

/// One device to check: its wheel (0-based), role and node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Device {
    /// Wheel index (0-based).
    pub wheel: usize,
    /// Role.
    pub role: Role,
    /// Node-ID.
    pub node: u8,
}

fn pdo_name(map_index: u16) -> String {
    if (od::TPDO_MAP..od::TPDO_MAP + 0x200).contains(&map_index) {
        format!("TPDO{}", map_index - od::TPDO_MAP + 1)
    } else {
        format!("RPDO{}", map_index - od::RPDO_MAP + 1)
    }
}

fn is_map_object(index: u16) -> bool {
    (od::RPDO_MAP..od::RPDO_MAP + 0x200).contains(&index)
        || (od::TPDO_MAP..od::TPDO_MAP + 0x200).contains(&index)
}

/// Checks a device's boot plan (`plan`, as [`Cia402Config::plan_for`] makes it, node 0 in
/// PDO COB-IDs) against its description; `extra` tells whether a step at (index, sub) comes
/// from the platform file's `[[cia402.sdo]]` list (for the message). The first problem is
/// returned.
pub fn check_plan(
    eds: &Eds,
    dev: Device,
    plan: &[SdoOp],
    extra: &dyn Fn(u16, u8) -> bool,
) -> Result<(), EdsError> {
    let fail = |index: u16, sub: u8, problem: PlanProblem| EdsError::Plan {
        path: eds.path.clone(),
        node: dev.node,
        role: dev.role,
        wheel: dev.wheel + 1,
        index,
        sub,
        problem,
    };
    // The mapping being built per mapping object: entries written to sub-indices ≥ 1.
    let mut mapping: BTreeMap<u16, BTreeMap<u8, u32>> = BTreeMap::new();
    for op in plan {
        let op = for_node(*op, dev.node);
        let (index, sub) = op.object();
        let entry = eds.get(index, sub);
        match op {
            SdoOp::Write { data, optional, .. } => {
                let Some(e) = entry else {
                    if optional {
                        continue;
                    }
                    // A mapping entry beyond the mapping object's last sub-index: too many
                    // objects for this PDO.
                    if is_map_object(index) && sub >= 1 && eds.has_index(index) {
                        let bits = mapping.get(&index).map_or(0, |m| {
                            m.values()
                                .map(|&r| u32::from(MapEntry::from_raw(r).bits))
                                .sum::<u32>()
                        }) + u32::from(MapEntry::from_raw(data.as_u32()).bits);
                        return Err(fail(
                            index,
                            0,
                            PlanProblem::Capacity {
                                pdo: pdo_name(index),
                                entries: u32::from(sub),
                                max_entries: eds.mapping_capacity(index),
                                bits,
                            },
                        ));
                    }
                    return Err(fail(
                        index,
                        sub,
                        PlanProblem::Missing {
                            write: true,
                            extra: extra(index, sub),
                        },
                    ));
                };
                if !e.access.writable() {
                    return Err(fail(
                        index,
                        sub,
                        PlanProblem::NotWritable {
                            access: e.access.name(),
                            extra: extra(index, sub),
                        },
                    ));
                }
                if let Some(size) = type_size(e.data_type) {
                    if size != data.len() {
                        return Err(fail(
                            index,
                            sub,
                            PlanProblem::Size {
                                plan: data.len(),
                                object: size,
                                data_type: e.data_type,
                            },
                        ));
                    }
                }
                let v = as_typed(&data, e.data_type);
                let low = e.low.map(|x| x.at(dev.node));
                let high = e.high.map(|x| x.at(dev.node));
                if low.is_some_and(|l| v < l) || high.is_some_and(|h| v > h) {
                    return Err(fail(
                        index,
                        sub,
                        PlanProblem::OutOfRange {
                            value: v,
                            low,
                            high,
                        },
                    ));
                }
                if is_map_object(index) {
                    let m = mapping.entry(index).or_default();
                    if sub == 0 {
                        let n = data.as_u32();
                        // Sub-index 0 = n makes entries 1..=n the mapping: check them.
                        let max = eds.mapping_capacity(index);
                        let mut bits = 0u32;
                        for s in 1..=n.min(64) as u8 {
                            let raw = m.get(&s).copied().unwrap_or(0);
                            let me = MapEntry::from_raw(raw);
                            bits += u32::from(me.bits);
                            let pdo = pdo_name(index);
                            let Some(obj) = eds.get(me.index, me.sub) else {
                                return Err(fail(
                                    me.index,
                                    me.sub,
                                    PlanProblem::Missing {
                                        write: false,
                                        extra: false,
                                    },
                                ));
                            };
                            if !obj.pdo_mapping {
                                return Err(fail(
                                    me.index,
                                    me.sub,
                                    PlanProblem::NotMappable {
                                        pdo,
                                        map_index: index,
                                    },
                                ));
                            }
                            if let Some(size) = type_size(obj.data_type) {
                                if 8 * size as u32 != u32::from(me.bits) {
                                    return Err(fail(
                                        me.index,
                                        me.sub,
                                        PlanProblem::MappedLength {
                                            pdo,
                                            bits: me.bits,
                                            object_bits: 8 * size as u32,
                                        },
                                    ));
                                }
                            }
                        }
                        if n > max || bits > 64 {
                            return Err(fail(
                                index,
                                0,
                                PlanProblem::Capacity {
                                    pdo: pdo_name(index),
                                    entries: n,
                                    max_entries: max,
                                    bits,
                                },
                            ));
                        }
                    } else {
                        m.insert(sub, data.as_u32());
                    }
                }
            }
            SdoOp::Verify {
                optional,
                mask,
                expected,
                what,
                poll_ms,
                ..
            } => {
                let Some(e) = entry else {
                    if optional {
                        continue;
                    }
                    return Err(fail(
                        index,
                        sub,
                        PlanProblem::Missing {
                            write: false,
                            extra: false,
                        },
                    ));
                };
                if !e.access.readable() {
                    return Err(fail(index, sub, PlanProblem::NotReadable));
                }
                // A configured value (DCF) the plan will compare: compare it now. Mode
                // displays (polled) follow a write of the plan's own and are left alone.
                if let (Some(p), 0) = (e.parameter, poll_ms) {
                    let dcf = (p.at(dev.node) as u32) & mask;
                    if dcf != expected {
                        return Err(fail(
                            index,
                            sub,
                            PlanProblem::DcfMismatch {
                                what,
                                dcf,
                                expected,
                            },
                        ));
                    }
                }
            }
        }
    }
    Ok(())
}

/// A DCF's value written at boot ([`dcf_writes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DcfWrite {
    /// Node-ID it is for.
    pub node: u8,
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Value, in the object's size.
    pub data: SdoData,
}

/// Why a DCF value is not written (listed by `rollbase config check`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DcfSkip {
    /// `ro` / `const`.
    NotWritable,
    /// The boot plan writes the object itself (a mandatory step).
    PlanOwned,
    /// A PDO parameter (0x1400–0x1BFF): the plan owns the PDOs.
    Pdo,
    /// 0x1010 / 0x1011 store and restore parameters.
    StoreRestore,
    /// Not 1–4 bytes (a string, a domain, a 64-bit value).
    NotExpedited,
}

impl DcfSkip {
    /// Short reason.
    pub fn reason(self) -> &'static str {
        match self {
            Self::NotWritable => "read-only",
            Self::PlanOwned => "the boot plan writes it",
            Self::Pdo => "PDO parameter (the plan configures the PDOs)",
            Self::StoreRestore => "store/restore parameters",
            Self::NotExpedited => "not 1-4 bytes",
        }
    }
}

/// The values of a DCF to write to the device at `node` whose own plan is `plan`: every
/// `ParameterValue` except those listed in the module docs (returned as skipped).
pub fn dcf_writes(eds: &Eds, node: u8, plan: &[SdoOp]) -> (Vec<DcfWrite>, Vec<DcfSkipped>) {
    let owned: BTreeSet<(u16, u8)> = plan
        .iter()
        .filter(|o| {
            matches!(
                o,
                SdoOp::Write {
                    optional: false,
                    ..
                }
            )
        })
        .map(|o| o.object())
        .collect();
    let mut writes = Vec::new();
    let mut skipped = Vec::new();
    for ((index, sub), e) in eds.entries() {
        let Some(p) = e.parameter else { continue };
        let skip = if (0x1400..=0x1BFF).contains(&index) {
            Some(DcfSkip::Pdo)
        } else if index == 0x1010 || index == 0x1011 {
            Some(DcfSkip::StoreRestore)
        } else if !e.access.writable() {
            Some(DcfSkip::NotWritable)
        } else if owned.contains(&(index, sub)) {
            Some(DcfSkip::PlanOwned)
        } else if !matches!(type_size(e.data_type), Some(1..=4)) {
            Some(DcfSkip::NotExpedited)
        } else {
            None
        };
        if let Some(s) = skip {
            skipped.push(((index, sub), s));
            continue;
        }
        let size = type_size(e.data_type).unwrap_or(4) as u8;
        writes.push(DcfWrite {
            node,
            index,
            sub,
            data: SdoData::new(p.at(node) as u32, size),
        });
    }
    (writes, skipped)
}

/// What [`apply`] did, for `rollbase config check`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EdsReport {
    /// Per device checked: (node, role, file, vendor and product, DCF values written).
    pub devices: Vec<(u8, Role, String, String, usize)>,
    /// DCF values not written: (node, index, sub, why).
    pub skipped: Vec<(u8, u16, u8, DcfSkip)>,
}

/// Loads the description files `cfg.eds` names (relative paths against `base`), takes the
/// DCFs' values into `cfg.dcf` and checks every device's boot plan (for a control period of
/// `period_us`) against its file. Devices without a file are not checked.
pub fn apply(cfg: &mut Cia402Config, base: &Path, period_us: u32) -> Result<EdsReport, EdsError> {
    let mut loaded: BTreeMap<String, Eds> = BTreeMap::new();
    let mut report = EdsReport::default();
    cfg.dcf.clear();
    let devices: Vec<(usize, Role, u8)> = cfg.devices().collect();
    // DCF values first (they become part of the plans), then the check of the full plans.
    let mut files: Vec<(usize, Role, u8, String)> = Vec::new();
    for &(wheel, role, node) in &devices {
        let Some(file) = cfg.eds.for_device(role, node) else {
            continue;
        };
        let path = base.join(file);
        let key = path.display().to_string();
        if !loaded.contains_key(&key) {
            loaded.insert(key.clone(), Eds::load(&path)?);
        }
        files.push((wheel, role, node, key));
    }
    // The plan's own steps (the platform file's list comes after the DCF anyway).
    let mut bare = cfg.clone();
    bare.sdo.clear();
    for (wheel, role, node, key) in &files {
        let eds = &loaded[key];
        if eds.dcf {
            let plan = bare.plan_for(*wheel, *role, period_us);
            let (w, s) = dcf_writes(eds, *node, &plan);
            cfg.dcf.extend(w);
            report
                .skipped
                .extend(s.into_iter().map(|((i, sub), why)| (*node, i, sub, why)));
        }
    }
    for (wheel, role, node, key) in &files {
        let eds = &loaded[key];
        let plan = cfg.plan_for(*wheel, *role, period_us);
        let extra = |index: u16, sub: u8| {
            cfg.sdo
                .iter()
                .any(|x| x.applies(*role, *node) && x.index == index && x.sub == sub)
        };
        check_plan(
            eds,
            Device {
                wheel: *wheel,
                role: *role,
                node: *node,
            },
            &plan,
            &extra,
        )?;
        let n_dcf = cfg.dcf.iter().filter(|d| d.node == *node).count();
        report.devices.push((
            *node,
            *role,
            key.clone(),
            format!("{} {}", eds.vendor, eds.product).trim().to_string(),
            n_dcf,
        ));
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINI: &str = "\
[DeviceInfo]
VendorName=Acme ; a comment
ProductName=Drive
NrOfRXPDO=1
NrOfTXPDO=1

[MandatoryObjects]
SupportedObjects=2
1=0x1000
2=0x1018

[OptionalObjects]
SupportedObjects=2
1=0x1800
2=0x6060

[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00020192
PDOMapping=0

[1018]
ParameterName=Identity
ObjectType=0x9
SubNumber=2

[1018sub0]
ParameterName=n
DataType=0x0005
AccessType=ro
DefaultValue=1

[1018sub1]
ParameterName=Vendor-ID
DataType=0x0007
AccessType=ro
DefaultValue=0

[1800]
ObjectType=9
SubNumber=2

[1800sub0]
DataType=0x0005
AccessType=ro
DefaultValue=1

[1800sub1]
DataType=0x0007
AccessType=rw
DefaultValue=$NODEID+0x180

[6060]
ParameterName=Modes of operation
DataType=0x0002
AccessType=rw
LowLimit=-1
HighLimit=10
PDOMapping=1
ParameterValue=9
";

    #[test]
    fn numbers_and_node_ids() {
        assert_eq!(Value::parse("0x1A").map(|v| v.at(0)), Some(26));
        assert_eq!(Value::parse("26").map(|v| v.at(0)), Some(26));
        assert_eq!(Value::parse("-3").map(|v| v.at(0)), Some(-3));
        assert_eq!(Value::parse("010").map(|v| v.at(0)), Some(8));
        assert_eq!(Value::parse("0").map(|v| v.at(0)), Some(0));
        assert_eq!(Value::parse("$NODEID+0x180").map(|v| v.at(5)), Some(0x185));
        assert_eq!(
            Value::parse("0x200 + $nodeid").map(|v| v.at(5)),
            Some(0x205)
        );
        assert_eq!(Value::parse("zz"), None);
        assert_eq!(Value::parse(""), None);
    }

    #[test]
    fn parses_objects_subs_access_limits_and_parameter_values() {
        let e = Eds::parse(MINI, "mini.dcf").expect("parses");
        assert_eq!(e.vendor, "Acme");
        assert_eq!(e.tx_pdos, Some(1));
        assert!(e.dcf);
        assert_eq!(e.get(0x1000, 0).map(|x| x.access), Some(Access::Ro));
        assert_eq!(
            e.get(0x1800, 1).and_then(|x| x.default).map(|v| v.at(3)),
            Some(0x183)
        );
        let m = e.get(0x6060, 0).expect("6060");
        assert_eq!(m.low.map(|v| v.at(0)), Some(-1));
        assert!(m.pdo_mapping);
        assert_eq!(m.parameter.map(|v| v.at(0)), Some(9));
        assert!(e.get(0x6061, 0).is_none());
    }

    #[test]
    fn malformed_files_are_refused_naming_the_line() {
        for (text, needle) in [
            ("[FileInfo]\nA=1\n", "no [DeviceInfo]"),
            ("[DeviceInfo]\n", "no [MandatoryObjects]"),
            (
                "[DeviceInfo]\n[MandatoryObjects]\nSupportedObjects=1\n1=0x1000\n",
                "has no [1000] section",
            ),
            ("[DeviceInfo]\nnonsense\n", "neither"),
            (
                "[DeviceInfo]\n[MandatoryObjects]\nSupportedObjects=1\n1=0x1000\n[1000]\nDataType=0x7\nAccessType=rx\n",
                "AccessType=rx",
            ),
        ] {
            let e = Eds::parse(text, "bad.eds").expect_err(text).to_string();
            assert!(e.contains(needle) && e.contains("bad.eds"), "{e}");
        }
    }
}
