//! One-line, human-readable descriptions of the CiA 402 profile's frames (for
//! `rollbase monitor --profile cia402`). Stateless: each frame is described on its own,
//! PDOs by the profile's mappings and the platform file's units.

use super::cob::{self, Cob};
use super::config::{Cia402Config, Role};
use super::ds402::{self, State as State402};
use super::emcy::{self, Emcy};
use super::nmt;
use super::pdo;
use super::sdo::{SdoRequest, SdoResponse};
use crate::frame::CanFrame;

/// The device at `node` in `cfg`, as (wheel index, role).
pub fn device_of(cfg: &Cia402Config, node: u8) -> Option<(usize, Role)> {
    cfg.devices()
        .find(|(_, _, n)| *n == node)
        .map(|(w, r, _)| (w, r))
}

fn who(cfg: &Cia402Config, node: u8) -> String {
    match device_of(cfg, node) {
        Some((w, r)) => format!("node {node} (wheel {} {r})", w + 1),
        None if node == cfg.master_node => format!("node {node} (master)"),
        None => format!("node {node} (not in the platform file)"),
    }
}

fn command_name(cw: u16) -> &'static str {
    match ds402::decode_controlword(cw, 0) {
        ds402::Command::Shutdown => "shutdown",
        ds402::Command::SwitchOn => "switch on",
        ds402::Command::EnableOperation => "enable operation",
        ds402::Command::DisableVoltage => "disable voltage",
        ds402::Command::QuickStop => "quick stop",
        ds402::Command::FaultReset => "fault reset",
    }
}

/// What the frame is and carries; `Err` with the reason when it is malformed or not part
/// of the profile.
pub fn describe(f: &CanFrame, cfg: &Cia402Config) -> Result<String, String> {
    let e = |x: super::CanOpenError| x.to_string();
    match cob::classify(f.id()) {
        Cob::Nmt => {
            let (cmd, node) = nmt::parse_command(f).map_err(e)?;
            let target = if node == 0 {
                "all nodes".to_string()
            } else {
                who(cfg, node)
            };
            Ok(format!("NMT {cmd:?} → {target}"))
        }
        Cob::Sync if nmt::is_sync(f) => Ok("SYNC".into()),
        Cob::Sync => Err(format!("SYNC with {} data bytes", f.len())),
        Cob::Emcy(node) => {
            let (_, m) = Emcy::parse(f).map_err(e)?;
            Ok(format!(
                "EMCY {}: 0x{:04X} {} (error register 0x{:02X})",
                who(cfg, node),
                m.code,
                emcy::describe(m.code),
                m.register
            ))
        }
        Cob::Heartbeat(node) => {
            let (_, s) = nmt::parse_heartbeat(f).map_err(e)?;
            Ok(match s {
                nmt::NmtState::BootUp => format!("boot-up {}", who(cfg, node)),
                s => format!("heartbeat {}: {s}", who(cfg, node)),
            })
        }
        Cob::SdoRx(node) => {
            let (_, r) = SdoRequest::parse(f).map_err(e)?;
            Ok(match r {
                SdoRequest::Download { index, sub, data } => format!(
                    "SDO write → {}: 0x{index:04X}:{sub:02X} = 0x{:X} ({} bytes)",
                    who(cfg, node),
                    data.as_u32(),
                    data.len()
                ),
                SdoRequest::Upload { index, sub } => {
                    format!("SDO read → {}: 0x{index:04X}:{sub:02X}", who(cfg, node))
                }
                SdoRequest::Abort { index, sub, code } => format!(
                    "SDO abort → {}: 0x{index:04X}:{sub:02X} {code}",
                    who(cfg, node)
                ),
            })
        }
        Cob::SdoTx(node) => {
            let (_, r) = SdoResponse::parse(f).map_err(e)?;
            Ok(match r {
                SdoResponse::DownloadAck { index, sub } => {
                    format!("SDO write ok ← {}: 0x{index:04X}:{sub:02X}", who(cfg, node))
                }
                SdoResponse::Upload { index, sub, data } => format!(
                    "SDO read ← {}: 0x{index:04X}:{sub:02X} = 0x{:X}",
                    who(cfg, node),
                    data.as_u32()
                ),
                SdoResponse::UploadSegmented { index, sub, size } => format!(
                    "SDO segmented upload ← {}: 0x{index:04X}:{sub:02X} size {size:?}",
                    who(cfg, node)
                ),
                SdoResponse::Abort { index, sub, code } => format!(
                    "SDO ABORT ← {}: 0x{index:04X}:{sub:02X} {code}",
                    who(cfg, node)
                ),
            })
        }
        Cob::Rpdo(1, node) => {
            let Some((_, role)) = device_of(cfg, node).filter(|(_, r)| *r != Role::Leg) else {
                return Err(format!("RPDO1 to {}: not a drive", who(cfg, node)));
            };
            let v = pdo::DRIVE_RPDO1.unpack(f).map_err(e)?;
            let cw = v[0] as u16;
            let units = if role == Role::Drive {
                cfg.drive
            } else {
                cfg.steer
            };
            Ok(format!(
                "RPDO1 → {}: controlword 0x{cw:04X} ({}{}), target velocity {} ({:.4} rad/s)",
                who(cfg, node),
                command_name(cw),
                if cw & ds402::CW_HALT != 0 {
                    ", halt"
                } else {
                    ""
                },
                v[1] as i32,
                units.velocity_to_si(v[1] as i32)
            ))
        }
        Cob::Tpdo(n, node) => {
            let Some((_, role)) = device_of(cfg, node) else {
                return Err(format!("TPDO{n} from {}", who(cfg, node)));
            };
            match (role, n) {
                (Role::Drive | Role::Steer, 1) => {
                    let v = pdo::DRIVE_TPDO1.unpack(f).map_err(e)?;
                    let u = if role == Role::Drive {
                        cfg.drive
                    } else {
                        cfg.steer
                    };
                    Ok(format!(
                        "TPDO1 ← {}: position {} ({:.4} rad), velocity {} ({:.4} rad/s)",
                        who(cfg, node),
                        v[0] as i32,
                        u.position_to_rad(v[0] as i32),
                        v[1] as i32,
                        u.velocity_to_si(v[1] as i32)
                    ))
                }
                (Role::Drive | Role::Steer, 2) => {
                    let v = pdo::DRIVE_TPDO2.unpack(f).map_err(e)?;
                    let sw = v[0] as u16;
                    let state = State402::from_statusword(sw)
                        .map_or("no valid state".to_string(), |s| s.to_string());
                    Ok(format!(
                        "TPDO2 ← {}: statusword 0x{sw:04X} ({state})",
                        who(cfg, node)
                    ))
                }
                (Role::Leg, 1) => {
                    let v = pdo::ENCODER_TPDO1.unpack(f).map_err(e)?;
                    let u = cfg.leg_encoder;
                    Ok(format!(
                        "TPDO1 ← {}: position {} ({:.6} m), speed {} ({:.5} m/s)",
                        who(cfg, node),
                        v[0],
                        u.position_to_m(v[0]),
                        v[1] as u16 as i16,
                        u.speed_to_si(v[1] as u16 as i16)
                    ))
                }
                _ => Err(format!(
                    "TPDO{n} from {}: not mapped by this profile",
                    who(cfg, node)
                )),
            }
        }
        Cob::Rpdo(n, node) => Err(format!(
            "RPDO{n} to {}: not mapped by this profile",
            who(cfg, node)
        )),
        Cob::Other => Err(format!(
            "id 0x{:03X} is not in the CANopen predefined connection set",
            f.id()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn describes_the_profile_frames() {
        let cfg = Cia402Config::for_wheels(4);
        let d = |id: u16, data: &[u8]| describe(&CanFrame::new(id, data).unwrap(), &cfg);
        assert_eq!(d(0x000, &[0x01, 0x00]).unwrap(), "NMT Start → all nodes");
        assert_eq!(d(0x080, &[]).unwrap(), "SYNC");
        assert_eq!(
            d(0x201, &[0x0F, 0x00, 0x18, 0xFC, 0xFF, 0xFF]).unwrap(),
            "RPDO1 → node 1 (wheel 1 rolling drive): controlword 0x000F (enable operation), target velocity -1000 (-0.0128 rad/s)"
        );
        assert_eq!(
            d(0x282, &[0x37, 0x06]).unwrap(),
            "TPDO2 ← node 2 (wheel 1 steering drive): statusword 0x0637 (operation enabled)"
        );
        assert!(d(0x189, &[0x50, 0xA5, 0x05, 0x00, 0xF4, 0xFF])
            .unwrap()
            .contains("0.370000 m"));
        assert!(d(0x084, &[0x10, 0x23, 0x02, 0, 0, 0, 0, 0])
            .unwrap()
            .contains("continuous over-current"));
        assert_eq!(
            d(0x709, &[0x00]).unwrap(),
            "boot-up node 9 (wheel 1 leg encoder)"
        );
        assert!(d(0x586, &[0x80, 0x60, 0x60, 0x00, 0x30, 0x00, 0x09, 0x06])
            .unwrap()
            .contains("0x06090030"));
        assert!(d(0x209, &[0; 6]).is_err(), "an encoder has no RPDO1");
        assert!(d(0x181, &[0; 6]).is_err(), "wrong length");
        assert!(d(0x7E5, &[]).is_err());
    }
}
