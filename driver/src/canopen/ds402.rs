//! The CiA 402 drive state machine ("power drive system" FSA, IEC 61800-7-201).
//!
//! ```text
//!                 Not ready to switch on ──(auto, T1)──► Switch on disabled ◄──────────────┐
//!                                                          │ ▲ Shutdown T2 / Disable      │
//!                                                          ▼ │ voltage, Quick stop T7     │ Fault
//!                                                   Ready to switch on                    │ reset
//!                                     Switch on T3 │ ▲ Shutdown T6          Disable       │ T15
//!                                                  ▼ │                      voltage T9,   │
//!                                               Switched on                 T10, T12      │
//!                          Enable operation T4 │ ▲ Disable operation T5                   │
//!                                              ▼ │                                      Fault
//!                                        Operation enabled ──Quick stop T11──►            ▲
//!                                              ▲        Quick stop active                 │ T14
//!                                              └──Enable operation T16──┘        Fault reaction
//!                                   (any state) ──error, T13──────────────────►     active
//! ```
//!
//! The statusword tells the state by bits 0–3, 5, 6 (masks 0x4F / 0x6F); the controlword
//! commands by bits 0–3 and 7 (fault reset on the rising edge of bit 7). Bit 8 of the
//! controlword is "halt".
//!
//! [`device_transition`] is the device side (used by the simulated drives);
//! [`master_controlword`] is the master's choice of the next controlword to reach a target.

/// Statusword bit: ready to switch on.
pub const SW_READY_TO_SWITCH_ON: u16 = 1 << 0;
/// Statusword bit: switched on.
pub const SW_SWITCHED_ON: u16 = 1 << 1;
/// Statusword bit: operation enabled.
pub const SW_OPERATION_ENABLED: u16 = 1 << 2;
/// Statusword bit: fault.
pub const SW_FAULT: u16 = 1 << 3;
/// Statusword bit: voltage enabled.
pub const SW_VOLTAGE_ENABLED: u16 = 1 << 4;
/// Statusword bit: quick stop (active low: 0 = quick stop active).
pub const SW_QUICK_STOP: u16 = 1 << 5;
/// Statusword bit: switch on disabled.
pub const SW_SWITCH_ON_DISABLED: u16 = 1 << 6;
/// Statusword bit: warning.
pub const SW_WARNING: u16 = 1 << 7;
/// Statusword bit: remote (the controlword is processed).
pub const SW_REMOTE: u16 = 1 << 9;
/// Statusword bit: target reached (CSV: the velocity follows the target).
pub const SW_TARGET_REACHED: u16 = 1 << 10;
/// Statusword bit: internal limit active.
pub const SW_INTERNAL_LIMIT: u16 = 1 << 11;
/// Statusword bit 12 in the cyclic synchronous modes: the drive follows the command value.
pub const SW_FOLLOWS_COMMAND: u16 = 1 << 12;

/// Controlword bit: switch on.
pub const CW_SWITCH_ON: u16 = 1 << 0;
/// Controlword bit: enable voltage.
pub const CW_ENABLE_VOLTAGE: u16 = 1 << 1;
/// Controlword bit: quick stop (active low).
pub const CW_QUICK_STOP: u16 = 1 << 2;
/// Controlword bit: enable operation.
pub const CW_ENABLE_OPERATION: u16 = 1 << 3;
/// Controlword bit: fault reset (rising edge).
pub const CW_FAULT_RESET: u16 = 1 << 7;
/// Controlword bit: halt.
pub const CW_HALT: u16 = 1 << 8;

/// Controlword "shutdown" (→ ready to switch on).
pub const CW_SHUTDOWN: u16 = 0x0006;
/// Controlword "switch on" / "disable operation" (→ switched on).
pub const CW_SWITCH_ON_CMD: u16 = 0x0007;
/// Controlword "enable operation" (→ operation enabled).
pub const CW_ENABLE_OPERATION_CMD: u16 = 0x000F;
/// Controlword "disable voltage" (→ switch on disabled).
pub const CW_DISABLE_VOLTAGE: u16 = 0x0000;
/// Controlword "quick stop" (→ quick stop active from operation enabled).
pub const CW_QUICK_STOP_CMD: u16 = 0x0002;

/// The states of the CiA 402 state machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum State {
    /// Initialising; no communication with the power stage yet.
    NotReadyToSwitchOn,
    /// Initialised; power stage off. Where a drive waits after boot and after a fault reset.
    SwitchOnDisabled,
    /// Power may be applied; drive function disabled.
    ReadyToSwitchOn,
    /// Power stage on; drive function disabled.
    SwitchedOn,
    /// Drive function enabled: the drive follows its setpoints.
    OperationEnabled,
    /// Quick stop in progress or completed (drive function enabled).
    QuickStopActive,
    /// A fault was detected; the drive is running its fault reaction.
    FaultReactionActive,
    /// Fault; drive function disabled until a fault reset.
    Fault,
}

impl State {
    /// The state the statusword shows, `None` for a statusword that matches no state.
    pub fn from_statusword(sw: u16) -> Option<State> {
        Some(match (sw & 0x4F, sw & 0x6F) {
            (0x00, _) => State::NotReadyToSwitchOn,
            (0x40, _) => State::SwitchOnDisabled,
            (_, 0x21) => State::ReadyToSwitchOn,
            (_, 0x23) => State::SwitchedOn,
            (_, 0x27) => State::OperationEnabled,
            (_, 0x07) => State::QuickStopActive,
            (0x0F, _) => State::FaultReactionActive,
            (0x08, _) => State::Fault,
            _ => return None,
        })
    }

    /// The state bits (0–3, 5, 6) of a statusword in this state.
    pub fn statusword_bits(self) -> u16 {
        match self {
            State::NotReadyToSwitchOn => 0x0000,
            State::SwitchOnDisabled => 0x0040,
            State::ReadyToSwitchOn => 0x0021,
            State::SwitchedOn => 0x0023,
            State::OperationEnabled => 0x0027,
            State::QuickStopActive => 0x0007,
            State::FaultReactionActive => 0x000F,
            State::Fault => 0x0008,
        }
    }

    /// True when the drive follows its setpoints.
    pub fn is_enabled(self) -> bool {
        self == State::OperationEnabled
    }

    /// True in Fault and Fault reaction active.
    pub fn is_fault(self) -> bool {
        matches!(self, State::Fault | State::FaultReactionActive)
    }

    /// Lower-case name as in the standard.
    pub fn name(self) -> &'static str {
        match self {
            State::NotReadyToSwitchOn => "not ready to switch on",
            State::SwitchOnDisabled => "switch on disabled",
            State::ReadyToSwitchOn => "ready to switch on",
            State::SwitchedOn => "switched on",
            State::OperationEnabled => "operation enabled",
            State::QuickStopActive => "quick stop active",
            State::FaultReactionActive => "fault reaction active",
            State::Fault => "fault",
        }
    }
}

impl std::fmt::Display for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A controlword command.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Command {
    /// x110: → ready to switch on.
    Shutdown,
    /// 0111: → switched on (from ready to switch on) or disable operation (from operation
    /// enabled).
    SwitchOn,
    /// 1111: → operation enabled (from switched on, ready to switch on or quick stop active).
    EnableOperation,
    /// xx0x: → switch on disabled.
    DisableVoltage,
    /// x01x: → quick stop active (from operation enabled) or switch on disabled.
    QuickStop,
    /// Rising edge of bit 7: fault → switch on disabled.
    FaultReset,
}

/// The command a controlword gives, given the previous controlword (for the fault-reset
/// edge). Bits other than 0–3 and 7 are ignored.
pub fn decode_controlword(cw: u16, previous: u16) -> Command {
    if cw & CW_FAULT_RESET != 0 && previous & CW_FAULT_RESET == 0 {
        return Command::FaultReset;
    }
    if cw & CW_ENABLE_VOLTAGE == 0 {
        Command::DisableVoltage
    } else if cw & CW_QUICK_STOP == 0 {
        Command::QuickStop
    } else if cw & CW_SWITCH_ON == 0 {
        Command::Shutdown
    } else if cw & CW_ENABLE_OPERATION == 0 {
        Command::SwitchOn
    } else {
        Command::EnableOperation
    }
}

/// The device's next state for a command (transitions T2–T12, T15, T16; T3 + T4 for
/// "enable operation" in ready to switch on). Commands that are not allowed in a state
/// leave it unchanged. Automatic transitions (T1, T13, T14, the end of a quick stop) are
/// the device's own business.
pub fn device_transition(state: State, cmd: Command) -> State {
    use Command as C;
    use State as S;
    match (state, cmd) {
        (S::SwitchOnDisabled, C::Shutdown) => S::ReadyToSwitchOn,
        (S::ReadyToSwitchOn, C::SwitchOn) => S::SwitchedOn,
        (S::ReadyToSwitchOn, C::EnableOperation) => S::OperationEnabled,
        (S::ReadyToSwitchOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled,
        (S::SwitchedOn, C::EnableOperation) => S::OperationEnabled,
        (S::SwitchedOn, C::Shutdown) => S::ReadyToSwitchOn,
        (S::SwitchedOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled,
        (S::OperationEnabled, C::SwitchOn) => S::SwitchedOn,
        (S::OperationEnabled, C::Shutdown) => S::ReadyToSwitchOn,
        (S::OperationEnabled, C::DisableVoltage) => S::SwitchOnDisabled,
        (S::OperationEnabled, C::QuickStop) => S::QuickStopActive,
        (S::QuickStopActive, C::DisableVoltage) => S::SwitchOnDisabled,
        (S::QuickStopActive, C::EnableOperation) => S::OperationEnabled,
        (S::Fault, C::FaultReset) => S::SwitchOnDisabled,
        (s, _) => s,
    }
}

/// The controlword the master sends to move a drive in `state` (`None`: no statusword seen
/// yet) toward operation enabled (`enable`) or toward ready to switch on (`!enable`: the
/// drive function disabled, power stage allowed), with `halt` (bit 8) while enabled.
///
/// A drive in Fault gets "disable voltage" unless `fault_reset` is asked for, then a fault
/// reset edge: 0x0080 when the previous controlword had bit 7 clear, else 0x0000 (so a
/// reset that did not take is retried every other cycle). One step per call: the state
/// machine needs the drive's confirmation (its statusword) between steps.
pub fn master_controlword(
    state: Option<State>,
    enable: bool,
    halt: bool,
    fault_reset: bool,
    previous: u16,
) -> u16 {
    let halt_bit = if halt { CW_HALT } else { 0 };
    match state {
        None | Some(State::NotReadyToSwitchOn) | Some(State::FaultReactionActive) => {
            CW_DISABLE_VOLTAGE
        }
        Some(State::Fault) => {
            if fault_reset && previous & CW_FAULT_RESET == 0 {
                CW_FAULT_RESET
            } else {
                CW_DISABLE_VOLTAGE
            }
        }
        Some(State::QuickStopActive) => CW_DISABLE_VOLTAGE,
        Some(_) if !enable => CW_SHUTDOWN,
        Some(State::SwitchOnDisabled) => CW_SHUTDOWN,
        Some(State::ReadyToSwitchOn) => CW_SWITCH_ON_CMD,
        Some(State::SwitchedOn) | Some(State::OperationEnabled) => {
            CW_ENABLE_OPERATION_CMD | halt_bit
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL: [State; 8] = [
        State::NotReadyToSwitchOn,
        State::SwitchOnDisabled,
        State::ReadyToSwitchOn,
        State::SwitchedOn,
        State::OperationEnabled,
        State::QuickStopActive,
        State::FaultReactionActive,
        State::Fault,
    ];

    #[test]
    fn statusword_round_trips_with_any_other_bits() {
        for s in ALL {
            for extra in [
                0u16,
                SW_VOLTAGE_ENABLED,
                SW_REMOTE | SW_TARGET_REACHED,
                0xFF80,
            ] {
                // Bits outside 0–3, 5, 6 never change the state (bit 5 is part of it for
                // the 0x6F states, so leave it to the state's own pattern).
                let sw = s.statusword_bits() | (extra & !0x006F);
                assert_eq!(State::from_statusword(sw), Some(s), "{s:?} 0x{sw:04X}");
            }
        }
        // Examples from drive manuals: 0x0250 switch on disabled, 0x0231 ready, 0x0233
        // switched on, 0x0237 operation enabled, 0x0218 fault.
        assert_eq!(
            State::from_statusword(0x0250),
            Some(State::SwitchOnDisabled)
        );
        assert_eq!(State::from_statusword(0x0231), Some(State::ReadyToSwitchOn));
        assert_eq!(State::from_statusword(0x0233), Some(State::SwitchedOn));
        assert_eq!(
            State::from_statusword(0x0237),
            Some(State::OperationEnabled)
        );
        assert_eq!(State::from_statusword(0x0218), Some(State::Fault));
        // No state: ready + switched on without quick-stop pattern match (0x0003 & 0x6F).
        assert_eq!(State::from_statusword(0x0001), None);
    }

    #[test]
    fn controlword_commands() {
        assert_eq!(decode_controlword(0x0006, 0), Command::Shutdown);
        assert_eq!(decode_controlword(0x0007, 0), Command::SwitchOn);
        assert_eq!(decode_controlword(0x000F, 0), Command::EnableOperation);
        assert_eq!(decode_controlword(0x010F, 0), Command::EnableOperation);
        assert_eq!(decode_controlword(0x0000, 0), Command::DisableVoltage);
        assert_eq!(decode_controlword(0x000D, 0), Command::DisableVoltage);
        assert_eq!(decode_controlword(0x0002, 0), Command::QuickStop);
        assert_eq!(decode_controlword(0x000B, 0), Command::QuickStop);
        assert_eq!(decode_controlword(0x0080, 0), Command::FaultReset);
        // No edge, no reset.
        assert_eq!(decode_controlword(0x0080, 0x0080), Command::DisableVoltage);
    }

    /// Drives the device and the master against each other from every state: the master
    /// reaches operation enabled (or ready to switch on) within 4 steps.
    #[test]
    fn master_reaches_its_target_from_every_state() {
        for start in ALL {
            for enable in [true, false] {
                let mut s = match start {
                    // Automatic transitions happen without the master.
                    State::NotReadyToSwitchOn => State::SwitchOnDisabled,
                    State::FaultReactionActive => State::Fault,
                    s => s,
                };
                let mut prev = 0u16;
                let mut steps = 0;
                let target = if enable {
                    State::OperationEnabled
                } else {
                    State::ReadyToSwitchOn
                };
                while s != target && steps < 8 {
                    let cw = master_controlword(Some(s), enable, false, true, prev);
                    s = device_transition(s, decode_controlword(cw, prev));
                    prev = cw;
                    steps += 1;
                }
                assert_eq!(s, target, "from {start:?}, enable {enable}");
                assert!(steps <= 4, "from {start:?}: {steps} steps");
            }
        }
    }

    #[test]
    fn a_fault_is_never_left_without_a_reset_request() {
        let mut prev = 0;
        for _ in 0..10 {
            let cw = master_controlword(Some(State::Fault), true, false, false, prev);
            assert_eq!(
                device_transition(State::Fault, decode_controlword(cw, prev)),
                State::Fault
            );
            prev = cw;
        }
        // With the request, the edge comes at once; a reset that did not take is retried
        // after a cycle with bit 7 clear.
        assert_eq!(
            master_controlword(Some(State::Fault), true, false, true, 0),
            0x0080
        );
        assert_eq!(
            master_controlword(Some(State::Fault), true, false, true, 0x0080),
            0x0000
        );
    }

    #[test]
    fn halt_only_while_enabled_and_unknown_state_gets_disable_voltage() {
        assert_eq!(
            master_controlword(Some(State::OperationEnabled), true, true, false, 0x0F),
            0x010F
        );
        assert_eq!(
            master_controlword(Some(State::SwitchOnDisabled), true, true, false, 0),
            0x0006
        );
        assert_eq!(master_controlword(None, true, false, false, 0), 0x0000);
        // Disabling from operation enabled: shutdown (→ ready to switch on).
        assert_eq!(
            master_controlword(Some(State::OperationEnabled), false, false, false, 0x0F),
            0x0006
        );
    }
}
