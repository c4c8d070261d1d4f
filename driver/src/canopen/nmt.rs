//! Network management: NMT commands, NMT states, boot-up and heartbeat, SYNC.
//!
//! - NMT command: id 0x000, 2 bytes `[command specifier, node-ID]` (node-ID 0 = all nodes).
//! - Boot-up: id 0x700 + node, 1 byte `0x00`, sent once when a device enters
//!   pre-operational after initialisation (power-on, reset node, reset communication).
//! - Heartbeat: id 0x700 + node, 1 byte = the NMT state (0x04 stopped, 0x05 operational,
//!   0x7F pre-operational), every producer heartbeat time (0x1017).
//! - SYNC: id 0x080 with no data (or 1 byte, the SYNC counter, when 0x1019 is configured;
//!   this profile does not use the counter).

use super::cob;
use super::CanOpenError;
use crate::frame::CanFrame;

/// NMT command specifiers (CiA 301 7.2.8.3.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NmtCommand {
    /// Start remote node → Operational.
    Start,
    /// Stop remote node → Stopped.
    Stop,
    /// Enter pre-operational.
    EnterPreOperational,
    /// Reset node (application and communication parameters), then boot-up.
    ResetNode,
    /// Reset communication (communication parameters only), then boot-up.
    ResetCommunication,
}

impl NmtCommand {
    /// The command specifier byte.
    pub fn specifier(self) -> u8 {
        match self {
            Self::Start => 0x01,
            Self::Stop => 0x02,
            Self::EnterPreOperational => 0x80,
            Self::ResetNode => 0x81,
            Self::ResetCommunication => 0x82,
        }
    }

    /// The command with this specifier.
    pub fn from_specifier(cs: u8) -> Option<Self> {
        Some(match cs {
            0x01 => Self::Start,
            0x02 => Self::Stop,
            0x80 => Self::EnterPreOperational,
            0x81 => Self::ResetNode,
            0x82 => Self::ResetCommunication,
            _ => return None,
        })
    }
}

/// NMT states as carried in boot-up and heartbeat messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NmtState {
    /// The boot-up message (0x00): the device just entered pre-operational.
    BootUp,
    /// Stopped (0x04).
    Stopped,
    /// Operational (0x05).
    Operational,
    /// Pre-operational (0x7F).
    PreOperational,
}

impl NmtState {
    /// The state byte.
    pub fn byte(self) -> u8 {
        match self {
            Self::BootUp => 0x00,
            Self::Stopped => 0x04,
            Self::Operational => 0x05,
            Self::PreOperational => 0x7F,
        }
    }

    /// The state with this byte (bit 7, the node-guarding toggle bit, is ignored).
    pub fn from_byte(b: u8) -> Option<Self> {
        Some(match b & 0x7F {
            0x00 => Self::BootUp,
            0x04 => Self::Stopped,
            0x05 => Self::Operational,
            0x7F => Self::PreOperational,
            _ => return None,
        })
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::BootUp => "boot-up",
            Self::Stopped => "stopped",
            Self::Operational => "operational",
            Self::PreOperational => "pre-operational",
        }
    }
}

impl std::fmt::Display for NmtState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

fn frame(id: u16, data: &[u8]) -> CanFrame {
    // Every id built here is ≤ 0x77F and every payload ≤ 2 bytes.
    CanFrame::new(id, data).unwrap_or_else(|_| unreachable!("NMT frames are always valid"))
}

/// An NMT command to `node` (0 = all nodes).
pub fn command(cmd: NmtCommand, node: u8) -> CanFrame {
    frame(cob::NMT, &[cmd.specifier(), node & 0x7F])
}

/// Parses an NMT command frame: (command, addressed node, 0 = all).
pub fn parse_command(f: &CanFrame) -> Result<(NmtCommand, u8), CanOpenError> {
    if f.id() != cob::NMT {
        return Err(CanOpenError::WrongId {
            what: "NMT command",
            id: f.id(),
        });
    }
    if f.len() != 2 {
        return Err(CanOpenError::WrongLength {
            what: "NMT command",
            id: f.id(),
            got: f.len(),
            expected: 2,
        });
    }
    let d = f.data();
    let cmd = NmtCommand::from_specifier(d[0]).ok_or(CanOpenError::BadValue {
        what: "NMT command specifier",
        value: d[0],
    })?;
    if d[1] > super::MAX_NODE_ID {
        return Err(CanOpenError::BadNode(d[1]));
    }
    Ok((cmd, d[1]))
}

/// A boot-up or heartbeat frame of `node` in `state`.
pub fn heartbeat(node: u8, state: NmtState) -> CanFrame {
    frame(cob::heartbeat(node), &[state.byte()])
}

/// Parses a boot-up or heartbeat frame: (node, state).
pub fn parse_heartbeat(f: &CanFrame) -> Result<(u8, NmtState), CanOpenError> {
    let cob::Cob::Heartbeat(node) = cob::classify(f.id()) else {
        return Err(CanOpenError::WrongId {
            what: "heartbeat",
            id: f.id(),
        });
    };
    if f.len() != 1 {
        return Err(CanOpenError::WrongLength {
            what: "heartbeat",
            id: f.id(),
            got: f.len(),
            expected: 1,
        });
    }
    let b = f.data()[0];
    let state = NmtState::from_byte(b).ok_or(CanOpenError::BadValue {
        what: "NMT state",
        value: b,
    })?;
    Ok((node, state))
}

/// A SYNC frame without counter.
pub fn sync() -> CanFrame {
    frame(cob::SYNC, &[])
}

/// True for a SYNC frame (with or without the 1-byte counter).
pub fn is_sync(f: &CanFrame) -> bool {
    f.id() == cob::SYNC && f.len() <= 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_nmt_frames() {
        // CiA 301: id 0, [cs, node].
        let f = command(NmtCommand::Start, 0);
        assert_eq!((f.id(), f.data()), (0x000, &[0x01, 0x00][..]));
        let f = command(NmtCommand::Stop, 5);
        assert_eq!(f.data(), &[0x02, 0x05]);
        assert_eq!(
            command(NmtCommand::EnterPreOperational, 127).data(),
            &[0x80, 0x7F]
        );
        assert_eq!(command(NmtCommand::ResetNode, 3).data(), &[0x81, 0x03]);
        assert_eq!(
            command(NmtCommand::ResetCommunication, 0).data(),
            &[0x82, 0x00]
        );
        for cmd in [
            NmtCommand::Start,
            NmtCommand::Stop,
            NmtCommand::EnterPreOperational,
            NmtCommand::ResetNode,
            NmtCommand::ResetCommunication,
        ] {
            assert_eq!(parse_command(&command(cmd, 9)), Ok((cmd, 9)));
        }
        let bad = CanFrame::new(0, &[0x03, 1]).unwrap();
        assert!(matches!(
            parse_command(&bad),
            Err(CanOpenError::BadValue { value: 3, .. })
        ));
        let short = CanFrame::new(0, &[0x01]).unwrap();
        assert!(matches!(
            parse_command(&short),
            Err(CanOpenError::WrongLength { got: 1, .. })
        ));
    }

    #[test]
    fn golden_heartbeat_and_boot_up() {
        let f = heartbeat(9, NmtState::BootUp);
        assert_eq!((f.id(), f.data()), (0x709, &[0x00][..]));
        assert_eq!(heartbeat(9, NmtState::Operational).data(), &[0x05]);
        assert_eq!(heartbeat(9, NmtState::PreOperational).data(), &[0x7F]);
        assert_eq!(heartbeat(9, NmtState::Stopped).data(), &[0x04]);
        assert_eq!(
            parse_heartbeat(&heartbeat(12, NmtState::Operational)),
            Ok((12, NmtState::Operational))
        );
        // Node guarding's toggle bit is ignored.
        let toggled = CanFrame::new(0x70C, &[0x85]).unwrap();
        assert_eq!(parse_heartbeat(&toggled), Ok((12, NmtState::Operational)));
        let bad = CanFrame::new(0x70C, &[0x06]).unwrap();
        assert!(parse_heartbeat(&bad).is_err());
        assert!(parse_heartbeat(&CanFrame::new(0x70C, &[]).unwrap()).is_err());
        assert!(parse_heartbeat(&CanFrame::new(0x60C, &[5]).unwrap()).is_err());
    }

    #[test]
    fn golden_sync() {
        let f = sync();
        assert_eq!((f.id(), f.len()), (0x080, 0));
        assert!(is_sync(&f));
        assert!(is_sync(&CanFrame::new(0x080, &[7]).unwrap()));
        assert!(!is_sync(&CanFrame::new(0x081, &[]).unwrap()));
    }
}
