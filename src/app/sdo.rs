//! `rollbase sdo`: read or write one object of a CANopen device, for bring-up and diagnosis.
//!
//! ```text
//! rollbase sdo --bus BUS --node N read INDEX:SUB [--type T]
//! rollbase sdo --bus BUS --node N write INDEX:SUB VALUE [--type T]
//! ```
//!
//! Expedited or segmented as the value needs (a string such as the device name 0x1008 is
//! segmented); the type says how the bytes are printed or how the value is encoded (`u8`,
//! `u16`, `u32`, `i8`, `i16`, `i32`, `str`, `hex`; a read prints unsigned, signed and hex
//! when no type is given). A master running on the bus (its SYNC seen within 100 ms) refuses
//! the command: stop `rollbase drive` first (its drives would see a second SDO client).

use super::common::CliError;
use clap::{Args, Subcommand, ValueEnum};
use rollbase_driver::bus::{self, CanBus};
use rollbase_driver::canopen::sdo::AbortCode;
use rollbase_driver::canopen::sdo_client::{SdoClient, Step};
use std::time::{Duration, Instant};

/// How long to listen for a running master's SYNC before talking.
const LISTEN: Duration = Duration::from_millis(100);

#[derive(Args, Debug)]
pub(crate) struct SdoArgs {
    /// CAN bus: an interface (can0) or socketcand://HOST:PORT/CHANNEL.
    #[arg(long)]
    bus: String,
    /// Node-ID of the device (1..=127).
    #[arg(long)]
    node: u8,
    /// Time to wait for each response (ms).
    #[arg(long, default_value_t = 500)]
    timeout_ms: u64,
    #[command(subcommand)]
    op: SdoOp,
}

#[derive(Subcommand, Debug)]
enum SdoOp {
    /// Read INDEX:SUB (hex, e.g. 0x603F:00 or 1008:0).
    Read {
        /// Object, INDEX:SUB.
        object: String,
        /// How to print the bytes.
        #[arg(long = "type", value_enum)]
        ty: Option<Type>,
    },
    /// Write VALUE to INDEX:SUB.
    Write {
        /// Object, INDEX:SUB.
        object: String,
        /// The value: a number (decimal or 0x hex) for the integer types, text for `str`,
        /// hex bytes for `hex` (e.g. 0a0b0c).
        value: String,
        /// The object's data type (its size on the wire).
        #[arg(long = "type", value_enum, default_value = "u32")]
        ty: Type,
    },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Type {
    U8,
    U16,
    U32,
    I8,
    I16,
    I32,
    Str,
    Hex,
}

fn usage(m: impl Into<String>) -> CliError {
    CliError::Usage(m.into())
}

/// `INDEX:SUB`, both hex (with or without 0x).
fn parse_object(s: &str) -> Result<(u16, u8), CliError> {
    let bad = || {
        usage(format!(
            "object `{s}`: expected INDEX:SUB in hex, e.g. 0x603F:00 or 1008:0"
        ))
    };
    let (i, sub) = s.split_once(':').ok_or_else(bad)?;
    let hex = |t: &str| {
        t.trim()
            .trim_start_matches("0x")
            .trim_start_matches("0X")
            .to_string()
    };
    let index = u16::from_str_radix(&hex(i), 16).map_err(|_| bad())?;
    let sub = u8::from_str_radix(&hex(sub), 16).map_err(|_| bad())?;
    Ok((index, sub))
}

fn encode(value: &str, ty: Type) -> Result<Vec<u8>, CliError> {
    let num = || -> Result<i64, CliError> {
        let v = value.trim();
        let r = if let Some(h) = v.strip_prefix("0x").or_else(|| v.strip_prefix("0X")) {
            i64::from_str_radix(h, 16)
        } else {
            v.parse::<i64>()
        };
        r.map_err(|_| {
            usage(format!(
                "value `{value}` is not a number (decimal or 0x hex)"
            ))
        })
    };
    let fit = |v: i64, lo: i64, hi: i64, n: usize| -> Result<Vec<u8>, CliError> {
        if v < lo || v > hi {
            return Err(usage(format!(
                "value {v} does not fit --type {ty:?} ({lo}..={hi})"
            )));
        }
        Ok(v.to_le_bytes()[..n].to_vec())
    };
    match ty {
        Type::U8 => fit(num()?, 0, 0xFF, 1),
        Type::U16 => fit(num()?, 0, 0xFFFF, 2),
        Type::U32 => fit(num()?, 0, 0xFFFF_FFFF, 4),
        Type::I8 => fit(num()?, -128, 127, 1),
        Type::I16 => fit(num()?, -32768, 32767, 2),
        Type::I32 => fit(num()?, i64::from(i32::MIN), i64::from(i32::MAX), 4),
        Type::Str => Ok(value.as_bytes().to_vec()),
        Type::Hex => {
            let v: String = value.chars().filter(|c| !c.is_whitespace()).collect();
            if !v.len().is_multiple_of(2) || v.is_empty() {
                return Err(usage(format!(
                    "hex bytes `{value}`: an even number of hex digits"
                )));
            }
            (0..v.len())
                .step_by(2)
                .map(|k| {
                    u8::from_str_radix(&v[k..k + 2], 16).map_err(|_| {
                        usage(format!(
                            "hex bytes `{value}`: `{}` is not hex",
                            &v[k..k + 2]
                        ))
                    })
                })
                .collect()
        }
    }
}

fn show(bytes: &[u8], ty: Option<Type>) -> String {
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    let mut raw = [0u8; 8];
    let n = bytes.len().min(8);
    raw[..n].copy_from_slice(&bytes[..n]);
    let u = u64::from_le_bytes(raw);
    let signed = |bits: u32| ((u << (64 - bits)) as i64) >> (64 - bits);
    match ty {
        Some(Type::Str) => String::from_utf8_lossy(bytes).into_owned(),
        Some(Type::Hex) => hex,
        Some(Type::U8 | Type::U16 | Type::U32) => u.to_string(),
        Some(Type::I8) => signed(8).to_string(),
        Some(Type::I16) => signed(16).to_string(),
        Some(Type::I32) => signed(32).to_string(),
        None if (1..=4).contains(&bytes.len()) => {
            format!(
                "{u} (0x{u:0w$X}, signed {})",
                signed(8 * bytes.len() as u32),
                w = 2 * bytes.len()
            )
        }
        None => {
            let text = bytes.iter().all(|b| b.is_ascii_graphic() || *b == b' ');
            if text {
                format!(
                    "\"{}\" ({} bytes)",
                    String::from_utf8_lossy(bytes),
                    bytes.len()
                )
            } else {
                format!("{hex} ({} bytes)", bytes.len())
            }
        }
    }
}

/// Refuses when another master runs on the bus: a SYNC within [`LISTEN`].
fn check_no_master(canbus: &mut dyn CanBus) -> Result<(), CliError> {
    let until = Instant::now() + LISTEN;
    while let Some(f) = canbus.recv_until(until)? {
        if f.frame.id() == 0x080 {
            return Err(usage(
                "a CANopen master is running on this bus (its SYNC was seen): stop `rollbase drive` (or the other master) first; two SDO clients on one device would disturb the running one",
            ));
        }
    }
    Ok(())
}

/// `rollbase sdo`.
pub(crate) fn sdo(a: SdoArgs) -> Result<i32, CliError> {
    if !(1..=127).contains(&a.node) {
        return Err(usage(format!("--node {}: a node-ID is 1..=127", a.node)));
    }
    let (object, first, ty) = match &a.op {
        SdoOp::Read { object, ty } => {
            let (index, sub) = parse_object(object)?;
            let (c, f) = SdoClient::upload(a.node, index, sub);
            ((c, f), true, *ty)
        }
        SdoOp::Write { object, value, ty } => {
            let (index, sub) = parse_object(object)?;
            let data = encode(value, *ty)?;
            let cf =
                SdoClient::download(a.node, index, sub, &data).map_err(|e| usage(e.to_string()))?;
            (cf, false, Some(*ty))
        }
    };
    let (mut client, frame) = object;
    let mut canbus = bus::open(&a.bus)?;
    check_no_master(canbus.as_mut())?;
    canbus.send(&frame)?;
    let timeout = Duration::from_millis(a.timeout_ms.clamp(10, 60_000));
    let (index, sub) = client.object();
    let mut deadline = Instant::now() + timeout;
    loop {
        let Some(f) = canbus.recv_until(deadline)? else {
            let _ = canbus.send(&client.abort_frame(AbortCode::Timeout));
            errln!(
                "node {}: no SDO response for 0x{index:04X}:{sub:02X} within {} ms: check the node-ID, that the device is powered and on this bus, and its bit rate",
                a.node,
                timeout.as_millis()
            );
            return Ok(1);
        };
        match client.on_frame(&f.frame) {
            Ok(Step::Ignore) => {}
            Ok(Step::Send(next)) => {
                canbus.send(&next)?;
                deadline = Instant::now() + timeout;
            }
            Ok(Step::Done(bytes)) => {
                if first {
                    outln!("{}", show(&bytes, ty));
                } else {
                    outln!("ok: wrote 0x{index:04X}:{sub:02X} of node {}", a.node);
                }
                return Ok(0);
            }
            Err(e) => {
                errln!("node {}: {e}", a.node);
                return Ok(1);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn objects_values_and_printing() {
        assert_eq!(parse_object("0x603F:00").unwrap(), (0x603F, 0));
        assert_eq!(parse_object("1008:0").unwrap(), (0x1008, 0));
        assert!(parse_object("603F").is_err());
        assert!(parse_object("0x1FFFF:0").is_err());
        assert_eq!(encode("0x10", Type::U16).unwrap(), vec![0x10, 0]);
        assert_eq!(encode("-2", Type::I16).unwrap(), vec![0xFE, 0xFF]);
        assert!(encode("300", Type::U8).is_err());
        assert_eq!(encode("0a0B", Type::Hex).unwrap(), vec![0x0A, 0x0B]);
        assert_eq!(show(&[0x37, 0x06], None), "1591 (0x0637, signed 1591)");
        assert_eq!(show(&[0xFE, 0xFF], Some(Type::I16)), "-2");
        assert_eq!(show(b"rollbase twin", None), "\"rollbase twin\" (13 bytes)");
    }
}
