//! The fault schedule: what goes wrong on the simulated modules' side of the bus, and when.
//!
//! Loadable from TOML (unknown keys and bad values are errors naming the field) and buildable
//! from command-line options ([`FaultArgs`], shared by `rollbase-sim` and any in-process user).
//! Times are seconds of simulator time (from its start), probabilities are in [0, 1].
//!
//! ```toml
//! seed = 7            # optional; the simulator's seed otherwise
//! loss = 0.01         # probability that a transmitted frame is lost
//! delay = 0.0005      # extra transmit delay (s)
//! jitter = 0.0002     # uniform extra delay in [0, jitter] (s)
//! duplicate = 0.001   # probability that a frame is sent twice
//! corrupt = 0.001     # probability that one payload bit is flipped (the CRC catches it)
//!
//! [[silent]]          # module sends nothing in [from, to)
//! node = 2
//! from = 1.0
//! to = 1.5
//!
//! [[motor_fault]]     # module latches an over-current fault at `at`
//! node = 3
//! at = 2.0
//!
//! [[encoder_stuck]]   # all encoders of the module freeze at `at`
//! node = 1
//! at = 3.0
//!
//! [[encoder_jump]]    # steering-encoder reading jumps by `amount` rad at `at`
//! node = 4
//! at = 4.0
//! amount = 0.3
//!
//! [[bus_off]]         # the simulator's bus connection is gone in [at, until)
//! at = 5.0
//! until = 5.2
//!
//! [[controller_bus_off]]  # lockstep: the controller's CAN interface is bus-off in
//! at = 6.0                # [at, until) (it reads the bus-off error frame, its sends fail,
//! until = 6.5             # it receives nothing), then restarted (restart-ms)
//!
//! [[power_cycle]]     # CiA 402: the device loses power at `at` and boots again (an
//! node = 4            # incremental steering counter restarts at 0 wherever the wheel is)
//! at = 7.0
//!
//! [[emcy]]            # CiA 402: the device sends an EMCY (register 0: informational);
//! node = 1            # a non-zero register with a drive faults it, 0x603F = code
//! at = 8.0
//! code = 0xFF01
//! register = 0
//!
//! [[drive_gain]]      # the module's rolling drive realises `gain` × its setpoint from `at`
//! node = 2            # (0.5: a motor that responds at 50 %, 0: one that does not respond)
//! at = 6.0
//! gain = 0.5
//! ```
//!
//! The per-frame faults (loss, delay, jitter, duplicate, corrupt) act on every frame the
//! simulated modules transmit, through `rollbase_driver::fault::FaultInjector`, so they are
//! deterministic from the seed.

use crate::error::{invalid, read_file, SimError};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A module sends nothing in `[from, to)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Silent {
    /// CAN node of the module (native profile, 1..=15) or of the CANopen device (CiA 402
    /// profile, 1..=127).
    pub node: u8,
    /// Start (s).
    pub from: f64,
    /// End (s), exclusive.
    pub to: f64,
}

/// A module's motor faults (over-current) at `at`; latched until a fault reset.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotorFault {
    /// CAN node of the module (native profile, 1..=15) or of the CANopen device (CiA 402
    /// profile, 1..=127).
    pub node: u8,
    /// Time (s).
    pub at: f64,
}

/// A CiA 402 device loses power at `at` and boots again (its boot time later).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PowerCycle {
    /// Node-ID of the CANopen device.
    pub node: u8,
    /// Time (s).
    pub at: f64,
}

/// A CiA 402 device sends an EMCY at `at`: with error register 0 an informational one (the
/// device goes on), otherwise a drive faults with `code` in 0x603F and 0x1003.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmcyEvent {
    /// Node-ID of the CANopen device.
    pub node: u8,
    /// Time (s).
    pub at: f64,
    /// Error code.
    pub code: u16,
    /// Error register.
    #[serde(default)]
    pub register: u8,
}

/// All encoders of a module freeze at their reading at `at` (for the rest of the run).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderStuck {
    /// CAN node of the module (native profile, 1..=15) or of the CANopen device (CiA 402
    /// profile, 1..=127).
    pub node: u8,
    /// Time (s).
    pub at: f64,
}

/// A module's steering-encoder reading jumps by `amount` (rad) at `at` and keeps the offset.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderJump {
    /// CAN node of the module (native profile, 1..=15) or of the CANopen device (CiA 402
    /// profile, 1..=127).
    pub node: u8,
    /// Time (s).
    pub at: f64,
    /// Jump (rad).
    pub amount: f64,
}

/// A module's rolling drive realises `gain` × its setpoint from `at` on (a weakened or dead
/// motor; see `PlantConfig::drive_gain` for all drives from the start).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveGain {
    /// CAN node of the module (native profile, 1..=15) or of the wheel's rolling drive (CiA
    /// 402 profile, 1..=127).
    pub node: u8,
    /// Time (s).
    pub at: f64,
    /// Fraction of the setpoint realised, in [0, 2].
    pub gain: f64,
}

/// The simulator's bus connection is gone in `[at, until)`: nothing is sent or received.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusOff {
    /// Start (s).
    pub at: f64,
    /// End (s), exclusive.
    pub until: f64,
}

/// The complete fault schedule. `FaultSchedule::default()` injects nothing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultSchedule {
    /// Seed for the per-frame faults; `None` = derived from the simulator's seed.
    pub seed: Option<u64>,
    /// Probability that a transmitted frame is lost.
    pub loss: f64,
    /// Extra transmit delay (s).
    pub delay: f64,
    /// Extra uniformly distributed delay in [0, jitter] (s).
    pub jitter: f64,
    /// Probability that a frame is transmitted twice.
    pub duplicate: f64,
    /// Probability that one payload bit of a frame is flipped.
    pub corrupt: f64,
    /// Modules going silent.
    pub silent: Vec<Silent>,
    /// Motor faults.
    pub motor_fault: Vec<MotorFault>,
    /// Encoders getting stuck.
    pub encoder_stuck: Vec<EncoderStuck>,
    /// Steering-encoder jumps.
    pub encoder_jump: Vec<EncoderJump>,
    /// Bus-off intervals.
    pub bus_off: Vec<BusOff>,
    /// Intervals in which the controller's CAN interface is bus-off (lockstep runs: the
    /// virtual bus puts the controller's node in bus-off and restarts it at `until`).
    pub controller_bus_off: Vec<BusOff>,
    /// Rolling drives that weaken or die.
    pub drive_gain: Vec<DriveGain>,
    /// CiA 402 devices that lose power and boot again.
    pub power_cycle: Vec<PowerCycle>,
    /// CiA 402 devices that send an EMCY.
    pub emcy: Vec<EmcyEvent>,
}

fn check_prob(field: &str, p: f64) -> Result<(), SimError> {
    if !p.is_finite() || !(0.0..=1.0).contains(&p) {
        return Err(invalid(field, p, "must be a probability in [0, 1]"));
    }
    Ok(())
}

fn check_time(field: &str, t: f64) -> Result<(), SimError> {
    if !t.is_finite() || t < 0.0 {
        return Err(invalid(field, t, "must be a finite time ≥ 0 s"));
    }
    Ok(())
}

fn check_node(field: &str, node: u8) -> Result<(), SimError> {
    if !(1..=127).contains(&node) {
        return Err(invalid(
            field,
            node,
            "node numbers are 1..=127 (wheel modules of the native profile: 1..=15)",
        ));
    }
    Ok(())
}

impl FaultSchedule {
    /// Parses and validates a schedule from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Self, SimError> {
        let s: FaultSchedule = toml::from_str(text).map_err(|e| SimError::Parse {
            what: "fault schedule".into(),
            message: e.to_string(),
        })?;
        s.validate()?;
        Ok(s)
    }

    /// Reads, parses and validates a schedule file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let path = path.as_ref();
        let text = read_file(path, "fault file")?;
        Self::from_toml_str(&text).map_err(|e| match e {
            SimError::Parse { message, .. } => SimError::Parse {
                what: format!("fault file {}", path.display()),
                message,
            },
            other => other,
        })
    }

    /// The schedule as TOML text (round-trips through [`FaultSchedule::from_toml_str`]).
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// True when the schedule injects nothing.
    pub fn is_empty(&self) -> bool {
        self.loss == 0.0
            && self.delay == 0.0
            && self.jitter == 0.0
            && self.duplicate == 0.0
            && self.corrupt == 0.0
            && self.silent.is_empty()
            && self.motor_fault.is_empty()
            && self.encoder_stuck.is_empty()
            && self.encoder_jump.is_empty()
            && self.bus_off.is_empty()
            && self.controller_bus_off.is_empty()
            && self.drive_gain.is_empty()
            && self.power_cycle.is_empty()
            && self.emcy.is_empty()
    }

    /// Checks every field; the error names the first bad one (e.g. `silent[1].to`).
    pub fn validate(&self) -> Result<(), SimError> {
        check_prob("loss", self.loss)?;
        check_prob("duplicate", self.duplicate)?;
        check_prob("corrupt", self.corrupt)?;
        for (name, v) in [("delay", self.delay), ("jitter", self.jitter)] {
            check_time(name, v)?;
            if v > 1.0 {
                return Err(invalid(name, v, "must be at most 1 s"));
            }
        }
        for (i, s) in self.silent.iter().enumerate() {
            check_node(&format!("silent[{i}].node"), s.node)?;
            check_time(&format!("silent[{i}].from"), s.from)?;
            check_time(&format!("silent[{i}].to"), s.to)?;
            if s.to <= s.from {
                return Err(invalid(
                    format!("silent[{i}].to"),
                    s.to,
                    format!("must be later than from = {}", s.from),
                ));
            }
        }
        for (i, m) in self.motor_fault.iter().enumerate() {
            check_node(&format!("motor_fault[{i}].node"), m.node)?;
            check_time(&format!("motor_fault[{i}].at"), m.at)?;
        }
        for (i, m) in self.encoder_stuck.iter().enumerate() {
            check_node(&format!("encoder_stuck[{i}].node"), m.node)?;
            check_time(&format!("encoder_stuck[{i}].at"), m.at)?;
        }
        for (i, m) in self.encoder_jump.iter().enumerate() {
            check_node(&format!("encoder_jump[{i}].node"), m.node)?;
            check_time(&format!("encoder_jump[{i}].at"), m.at)?;
            if !m.amount.is_finite() {
                return Err(invalid(
                    format!("encoder_jump[{i}].amount"),
                    m.amount,
                    "must be a finite angle in radians",
                ));
            }
        }
        for (i, g) in self.drive_gain.iter().enumerate() {
            check_node(&format!("drive_gain[{i}].node"), g.node)?;
            check_time(&format!("drive_gain[{i}].at"), g.at)?;
            let max = crate::plant::MAX_DRIVE_GAIN;
            if !(g.gain.is_finite() && (0.0..=max).contains(&g.gain)) {
                return Err(invalid(
                    format!("drive_gain[{i}].gain"),
                    g.gain,
                    format!("must be in [0, {max}] (1 = healthy, 0.5 = responds at 50 %, 0 = does not respond)"),
                ));
            }
        }
        for (i, m) in self.power_cycle.iter().enumerate() {
            check_node(&format!("power_cycle[{i}].node"), m.node)?;
            check_time(&format!("power_cycle[{i}].at"), m.at)?;
        }
        for (i, m) in self.emcy.iter().enumerate() {
            check_node(&format!("emcy[{i}].node"), m.node)?;
            check_time(&format!("emcy[{i}].at"), m.at)?;
        }
        for (i, b) in self.controller_bus_off.iter().enumerate() {
            check_time(&format!("controller_bus_off[{i}].at"), b.at)?;
            check_time(&format!("controller_bus_off[{i}].until"), b.until)?;
            if b.until <= b.at {
                return Err(invalid(
                    format!("controller_bus_off[{i}].until"),
                    b.until,
                    format!("must be later than at = {}", b.at),
                ));
            }
        }
        for (i, b) in self.bus_off.iter().enumerate() {
            check_time(&format!("bus_off[{i}].at"), b.at)?;
            check_time(&format!("bus_off[{i}].until"), b.until)?;
            if b.until <= b.at {
                return Err(invalid(
                    format!("bus_off[{i}].until"),
                    b.until,
                    format!("must be later than at = {}", b.at),
                ));
            }
        }
        Ok(())
    }

    /// Checks that every node named by an event is one of `nodes` (the platform's modules).
    pub fn check_nodes(&self, nodes: &[u8]) -> Result<(), SimError> {
        let check = |field: String, node: u8| {
            if nodes.contains(&node) {
                Ok(())
            } else {
                Err(invalid(
                    field,
                    node,
                    format!("no wheel module with this node on the platform (nodes {nodes:?})"),
                ))
            }
        };
        for (i, s) in self.silent.iter().enumerate() {
            check(format!("silent[{i}].node"), s.node)?;
        }
        for (i, m) in self.motor_fault.iter().enumerate() {
            check(format!("motor_fault[{i}].node"), m.node)?;
        }
        for (i, m) in self.encoder_stuck.iter().enumerate() {
            check(format!("encoder_stuck[{i}].node"), m.node)?;
        }
        for (i, m) in self.encoder_jump.iter().enumerate() {
            check(format!("encoder_jump[{i}].node"), m.node)?;
        }
        for (i, g) in self.drive_gain.iter().enumerate() {
            check(format!("drive_gain[{i}].node"), g.node)?;
        }
        for (i, g) in self.power_cycle.iter().enumerate() {
            check(format!("power_cycle[{i}].node"), g.node)?;
        }
        for (i, g) in self.emcy.iter().enumerate() {
            check(format!("emcy[{i}].node"), g.node)?;
        }
        Ok(())
    }

    /// Whether module `node` is silenced at time `t` (s).
    pub fn is_silent(&self, node: u8, t: f64) -> bool {
        self.silent
            .iter()
            .any(|s| s.node == node && t >= s.from && t < s.to)
    }

    /// Whether the bus is off at time `t` (s).
    pub fn is_bus_off(&self, t: f64) -> bool {
        self.bus_off.iter().any(|b| t >= b.at && t < b.until)
    }

    /// Whether the controller's interface is bus-off at time `t` (s).
    pub fn is_controller_bus_off(&self, t: f64) -> bool {
        self.controller_bus_off
            .iter()
            .any(|b| t >= b.at && t < b.until)
    }
}

fn parse_fields<const N: usize>(
    option: &str,
    text: &str,
    what: &str,
) -> Result<[f64; N], SimError> {
    let parts: Vec<&str> = text.split(':').collect();
    if parts.len() != N {
        return Err(invalid(
            option,
            format!("{text:?}"),
            format!("expected {what} ({N} values separated by ':')"),
        ));
    }
    let mut out = [0.0; N];
    for (o, p) in out.iter_mut().zip(&parts) {
        *o = p.trim().parse::<f64>().map_err(|_| {
            invalid(
                option,
                format!("{text:?}"),
                format!("`{p}` is not a number; expected {what}"),
            )
        })?;
    }
    Ok(out)
}

fn node_of(option: &str, text: &str, v: f64) -> Result<u8, SimError> {
    if v.fract() != 0.0 || !(1.0..=15.0).contains(&v) {
        return Err(invalid(
            option,
            format!("{text:?}"),
            "the node must be an integer in 1..=15",
        ));
    }
    Ok(v as u8)
}

/// Parses `NODE:FROM:TO` (seconds) for `--silent`.
pub fn parse_silent(text: &str) -> Result<Silent, SimError> {
    let [n, from, to] = parse_fields::<3>("--silent", text, "NODE:FROM:TO")?;
    Ok(Silent {
        node: node_of("--silent", text, n)?,
        from,
        to,
    })
}

/// Parses `NODE:AT` for `--motor-fault`.
pub fn parse_motor_fault(text: &str) -> Result<MotorFault, SimError> {
    let [n, at] = parse_fields::<2>("--motor-fault", text, "NODE:AT")?;
    Ok(MotorFault {
        node: node_of("--motor-fault", text, n)?,
        at,
    })
}

/// Parses `NODE:AT` for `--encoder-stuck`.
pub fn parse_encoder_stuck(text: &str) -> Result<EncoderStuck, SimError> {
    let [n, at] = parse_fields::<2>("--encoder-stuck", text, "NODE:AT")?;
    Ok(EncoderStuck {
        node: node_of("--encoder-stuck", text, n)?,
        at,
    })
}

/// Parses `NODE:AT:AMOUNT` (s, rad) for `--encoder-jump`.
pub fn parse_encoder_jump(text: &str) -> Result<EncoderJump, SimError> {
    let [n, at, amount] = parse_fields::<3>("--encoder-jump", text, "NODE:AT:AMOUNT")?;
    Ok(EncoderJump {
        node: node_of("--encoder-jump", text, n)?,
        at,
        amount,
    })
}

/// Parses `NODE:AT:GAIN` (s, fraction) for `--drive-gain`.
pub fn parse_drive_gain(text: &str) -> Result<DriveGain, SimError> {
    let [n, at, gain] = parse_fields::<3>("--drive-gain", text, "NODE:AT:GAIN")?;
    Ok(DriveGain {
        node: node_of("--drive-gain", text, n)?,
        at,
        gain,
    })
}

/// Parses `AT:UNTIL` (s) for `--bus-off`.
pub fn parse_bus_off(text: &str) -> Result<BusOff, SimError> {
    let [at, until] = parse_fields::<2>("--bus-off", text, "AT:UNTIL")?;
    Ok(BusOff { at, until })
}

/// Command-line options that add to (or override parts of) a [`FaultSchedule`].
/// Flatten into a clap parser with `#[command(flatten)]`.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct FaultArgs {
    /// Fault schedule file (TOML); the options below override/extend it.
    #[arg(long, value_name = "FILE")]
    pub faults: Option<std::path::PathBuf>,
    /// Probability that a frame sent by the modules is lost.
    #[arg(long, value_name = "P")]
    pub loss: Option<f64>,
    /// Extra transmit delay (ms).
    #[arg(long, value_name = "MS")]
    pub delay_ms: Option<f64>,
    /// Extra uniform transmit jitter in [0, MS] (ms).
    #[arg(long, value_name = "MS")]
    pub jitter_ms: Option<f64>,
    /// Probability that a frame is sent twice.
    #[arg(long, value_name = "P")]
    pub duplicate: Option<f64>,
    /// Probability that one payload bit of a frame is flipped.
    #[arg(long, value_name = "P")]
    pub corrupt: Option<f64>,
    /// A module goes silent: NODE:FROM:TO (seconds). Repeatable.
    #[arg(long, value_name = "NODE:FROM:TO", value_parser = parse_silent)]
    pub silent: Vec<Silent>,
    /// A module's motor faults: NODE:AT (seconds). Repeatable.
    #[arg(long, value_name = "NODE:AT", value_parser = parse_motor_fault)]
    pub motor_fault: Vec<MotorFault>,
    /// A module's encoders freeze: NODE:AT (seconds). Repeatable.
    #[arg(long, value_name = "NODE:AT", value_parser = parse_encoder_stuck)]
    pub encoder_stuck: Vec<EncoderStuck>,
    /// A module's steering encoder jumps: NODE:AT:AMOUNT (seconds, radians). Repeatable.
    #[arg(long, value_name = "NODE:AT:RAD", value_parser = parse_encoder_jump)]
    pub encoder_jump: Vec<EncoderJump>,
    /// The bus goes away: AT:UNTIL (seconds). Repeatable.
    #[arg(long, value_name = "AT:UNTIL", value_parser = parse_bus_off)]
    pub bus_off: Vec<BusOff>,
    /// A module's rolling drive realises GAIN × its setpoint from AT: NODE:AT:GAIN (seconds,
    /// fraction; 0.5 = responds at 50 %, 0 = does not respond). Repeatable.
    #[arg(long, value_name = "NODE:AT:GAIN", value_parser = parse_drive_gain)]
    pub drive_gain: Vec<DriveGain>,
}

impl FaultArgs {
    /// Builds the schedule: the file (if any), then the options on top; validated.
    pub fn to_schedule(&self) -> Result<FaultSchedule, SimError> {
        let mut s = match &self.faults {
            Some(path) => FaultSchedule::load(path)?,
            None => FaultSchedule::default(),
        };
        if let Some(v) = self.loss {
            s.loss = v;
        }
        if let Some(v) = self.delay_ms {
            s.delay = v * 1e-3;
        }
        if let Some(v) = self.jitter_ms {
            s.jitter = v * 1e-3;
        }
        if let Some(v) = self.duplicate {
            s.duplicate = v;
        }
        if let Some(v) = self.corrupt {
            s.corrupt = v;
        }
        s.silent.extend_from_slice(&self.silent);
        s.motor_fault.extend_from_slice(&self.motor_fault);
        s.encoder_stuck.extend_from_slice(&self.encoder_stuck);
        s.encoder_jump.extend_from_slice(&self.encoder_jump);
        s.bus_off.extend_from_slice(&self.bus_off);
        s.drive_gain.extend_from_slice(&self.drive_gain);
        s.validate()?;
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FULL: &str = r#"
seed = 7
loss = 0.01
delay = 0.0005
jitter = 0.0002
duplicate = 0.001
corrupt = 0.002

[[silent]]
node = 2
from = 1.0
to = 1.5

[[motor_fault]]
node = 3
at = 2.0

[[encoder_stuck]]
node = 1
at = 3.0

[[encoder_jump]]
node = 4
at = 4.0
amount = 0.3

[[bus_off]]
at = 5.0
until = 5.2

[[drive_gain]]
node = 2
at = 6.0
gain = 0.5
"#;

    #[test]
    fn full_schedule_parses_and_round_trips() {
        let s = FaultSchedule::from_toml_str(FULL).unwrap();
        assert_eq!(s.seed, Some(7));
        assert_eq!(s.loss, 0.01);
        assert_eq!(
            s.silent,
            vec![Silent {
                node: 2,
                from: 1.0,
                to: 1.5
            }]
        );
        assert_eq!(s.encoder_jump[0].amount, 0.3);
        assert_eq!(s.bus_off[0].until, 5.2);
        assert_eq!(
            s.drive_gain,
            vec![DriveGain {
                node: 2,
                at: 6.0,
                gain: 0.5
            }]
        );
        assert!(s.is_silent(2, 1.2) && !s.is_silent(2, 1.5) && !s.is_silent(1, 1.2));
        assert!(s.is_bus_off(5.0) && !s.is_bus_off(5.2));
        let back = FaultSchedule::from_toml_str(&s.to_toml_string()).unwrap();
        assert_eq!(s, back);
        assert!(FaultSchedule::from_toml_str("").unwrap().is_empty());
    }

    #[test]
    fn unknown_key_is_named() {
        let e = FaultSchedule::from_toml_str("lose = 0.1").unwrap_err();
        assert!(matches!(e, SimError::Parse { .. }));
        assert!(e.to_string().contains("lose"), "{e}");
        let e =
            FaultSchedule::from_toml_str("[[silent]]\nnode = 1\nfrom = 0.0\nto = 1.0\nuntil = 2.0")
                .unwrap_err();
        assert!(e.to_string().contains("until"), "{e}");
    }

    fn field_of(text: &str) -> String {
        match FaultSchedule::from_toml_str(text) {
            Err(SimError::Invalid { field, .. }) => field,
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn bad_values_name_the_field() {
        assert_eq!(field_of("loss = 1.5"), "loss");
        assert_eq!(field_of("jitter = -0.1"), "jitter");
        assert_eq!(field_of("delay = 2.0"), "delay");
        assert_eq!(
            field_of("[[silent]]\nnode = 1\nfrom = 2.0\nto = 1.0"),
            "silent[0].to"
        );
        assert_eq!(
            field_of("[[motor_fault]]\nnode = 0\nat = 1.0"),
            "motor_fault[0].node"
        );
        assert_eq!(
            field_of("[[bus_off]]\nat = 1.0\nuntil = 1.0"),
            "bus_off[0].until"
        );
        assert_eq!(
            field_of("[[encoder_stuck]]\nnode = 2\nat = -1.0"),
            "encoder_stuck[0].at"
        );
        assert_eq!(
            field_of("[[drive_gain]]\nnode = 2\nat = 1.0\ngain = -0.5"),
            "drive_gain[0].gain"
        );
        let s = FaultSchedule::from_toml_str("[[encoder_jump]]\nnode = 9\nat = 1.0\namount = 0.1")
            .unwrap();
        match s.check_nodes(&[1, 2, 3, 4]) {
            Err(SimError::Invalid { field, .. }) => assert_eq!(field, "encoder_jump[0].node"),
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn cli_options_parse_and_name_the_option() {
        assert_eq!(
            parse_silent("2:1.0:1.5").unwrap(),
            Silent {
                node: 2,
                from: 1.0,
                to: 1.5
            }
        );
        assert_eq!(
            parse_motor_fault("3:2").unwrap(),
            MotorFault { node: 3, at: 2.0 }
        );
        assert_eq!(
            parse_encoder_jump("4:4.0:-0.3").unwrap(),
            EncoderJump {
                node: 4,
                at: 4.0,
                amount: -0.3
            }
        );
        assert_eq!(
            parse_bus_off("5:5.2").unwrap(),
            BusOff {
                at: 5.0,
                until: 5.2
            }
        );
        for (res, opt) in [
            (parse_silent("2:1.0").map(|_| ()), "--silent"),
            (parse_motor_fault("x:1").map(|_| ()), "--motor-fault"),
            (parse_encoder_stuck("1.5:1").map(|_| ()), "--encoder-stuck"),
            (parse_encoder_jump("1:1").map(|_| ()), "--encoder-jump"),
        ] {
            match res {
                Err(SimError::Invalid { field, .. }) => assert_eq!(field, opt),
                other => panic!("expected Invalid for {opt}, got {other:?}"),
            }
        }
        let args = FaultArgs {
            loss: Some(0.2),
            delay_ms: Some(1.5),
            silent: vec![Silent {
                node: 1,
                from: 0.5,
                to: 0.7,
            }],
            ..FaultArgs::default()
        };
        let s = args.to_schedule().unwrap();
        assert_eq!(s.loss, 0.2);
        assert!((s.delay - 0.0015).abs() < 1e-15);
        assert_eq!(s.silent.len(), 1);
        let bad = FaultArgs {
            loss: Some(-1.0),
            ..FaultArgs::default()
        };
        assert!(
            matches!(bad.to_schedule(), Err(SimError::Invalid { field, .. }) if field == "loss")
        );
    }
}
