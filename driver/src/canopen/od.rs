//! Object dictionary indices the master writes and the simulated devices serve.
//!
//! CiA 301 communication objects, CiA 402 drive objects and CiA 406 encoder objects, with
//! their CANopen data types noted (the SDO and PDO code works on raw little-endian bytes).

/// Device type (UNSIGNED32): low word = device profile number, high word = profile-specific
/// type (CiA 301 7.5.2.1).
pub const DEVICE_TYPE: u16 = 0x1000;
/// Error register (UNSIGNED8).
pub const ERROR_REGISTER: u16 = 0x1001;
/// COB-ID SYNC (UNSIGNED32).
pub const COB_ID_SYNC: u16 = 0x1005;
/// Communication cycle period (UNSIGNED32, µs).
pub const COMM_CYCLE_PERIOD: u16 = 0x1006;
/// Consumer heartbeat time (ARRAY of UNSIGNED32: node-ID << 16 | time in ms).
pub const CONSUMER_HEARTBEAT: u16 = 0x1016;
/// Producer heartbeat time (UNSIGNED16, ms).
pub const PRODUCER_HEARTBEAT: u16 = 0x1017;
/// Identity object (RECORD: 1 vendor-ID, 2 product code, 3 revision, 4 serial number).
pub const IDENTITY: u16 = 0x1018;
/// RPDO communication parameters, RPDO n at 0x1400 + n − 1.
pub const RPDO_COMM: u16 = 0x1400;
/// RPDO mapping parameters, RPDO n at 0x1600 + n − 1.
pub const RPDO_MAP: u16 = 0x1600;
/// TPDO communication parameters, TPDO n at 0x1800 + n − 1.
pub const TPDO_COMM: u16 = 0x1800;
/// TPDO mapping parameters, TPDO n at 0x1A00 + n − 1.
pub const TPDO_MAP: u16 = 0x1A00;

/// PDO communication parameter sub-index: COB-ID (UNSIGNED32, bit 31 = not valid).
pub const PDO_COB_ID: u8 = 1;
/// PDO communication parameter sub-index: transmission type (UNSIGNED8).
pub const PDO_TRANSMISSION: u8 = 2;
/// PDO communication parameter sub-index: inhibit time (UNSIGNED16, 100 µs; TPDO only).
pub const PDO_INHIBIT: u8 = 3;
/// PDO communication parameter sub-index: event timer (UNSIGNED16, ms; on an RPDO the
/// deadline-monitoring time).
pub const PDO_EVENT_TIMER: u8 = 5;
/// Bit 31 of a PDO COB-ID entry: the PDO is not valid (disabled).
pub const PDO_COB_INVALID: u32 = 1 << 31;
/// Bit 30 of a TPDO COB-ID entry: no RTR allowed on this PDO.
pub const PDO_COB_NO_RTR: u32 = 1 << 30;

/// CiA 402: abort connection option code (INTEGER16): what the drive does on a
/// communication loss (heartbeat or RPDO timeout) while in Operation enabled.
pub const ABORT_CONNECTION_OPTION: u16 = 0x6007;
/// CiA 402: controlword (UNSIGNED16).
pub const CONTROLWORD: u16 = 0x6040;
/// CiA 402: statusword (UNSIGNED16).
pub const STATUSWORD: u16 = 0x6041;
/// CiA 402: modes of operation (INTEGER8).
pub const MODES_OF_OPERATION: u16 = 0x6060;
/// CiA 402: modes of operation display (INTEGER8).
pub const MODES_OF_OPERATION_DISPLAY: u16 = 0x6061;
/// CiA 402: position actual value (INTEGER32, increments).
pub const POSITION_ACTUAL: u16 = 0x6064;
/// CiA 402: velocity actual value (INTEGER32, velocity units).
pub const VELOCITY_ACTUAL: u16 = 0x606C;
/// CiA 402: interpolation time period (RECORD: 1 value UNSIGNED8, 2 index INTEGER8;
/// period = value · 10^index s), used by the cyclic synchronous modes.
pub const INTERPOLATION_TIME_PERIOD: u16 = 0x60C2;
/// CiA 402: target velocity (INTEGER32, velocity units).
pub const TARGET_VELOCITY: u16 = 0x60FF;

/// Pre-defined error field (ARRAY of UNSIGNED32: sub 0 number of errors, sub 1 the newest:
/// error code in the low word, manufacturer information in the high word).
pub const PRE_DEFINED_ERROR_FIELD: u16 = 0x1003;
/// Manufacturer device name (VISIBLE_STRING, usually longer than 4 bytes: a segmented
/// upload).
pub const DEVICE_NAME: u16 = 0x1008;
/// Manufacturer software version (VISIBLE_STRING).
pub const SOFTWARE_VERSION: u16 = 0x100A;
/// CiA 402: error code (UNSIGNED16): the drive's last error.
pub const ERROR_CODE: u16 = 0x603F;
/// CiA 402: quick stop option code (INTEGER16).
pub const QUICK_STOP_OPTION: u16 = 0x605A;
/// CiA 402: fault reaction option code (INTEGER16).
pub const FAULT_REACTION_OPTION: u16 = 0x605E;
/// CiA 402: home offset (INTEGER32, position units).
pub const HOME_OFFSET: u16 = 0x607C;
/// CiA 402: quick stop deceleration (UNSIGNED32, acceleration units).
pub const QUICK_STOP_DECELERATION: u16 = 0x6085;
/// CiA 402: polarity (UNSIGNED8: bit 7 position, bit 6 velocity).
pub const POLARITY: u16 = 0x607E;
/// CiA 402: position encoder resolution (sub 1 encoder increments, sub 2 motor revolutions).
pub const POSITION_ENCODER_RESOLUTION: u16 = 0x608F;
/// CiA 402: gear ratio (sub 1 motor revolutions, sub 2 shaft revolutions).
pub const GEAR_RATIO: u16 = 0x6091;
/// CiA 402: homing method (INTEGER8).
pub const HOMING_METHOD: u16 = 0x6098;
/// CiA 402: homing speeds (sub 1 during search for switch, sub 2 during search for zero;
/// UNSIGNED32, velocity units).
pub const HOMING_SPEEDS: u16 = 0x6099;
/// CiA 402: homing acceleration (UNSIGNED32, acceleration units).
pub const HOMING_ACCELERATION: u16 = 0x609A;
/// CiA 402: SI unit velocity (UNSIGNED32).
pub const SI_UNIT_VELOCITY: u16 = 0x60A9;
/// CiA 402: digital inputs (UNSIGNED32: bit 0 negative limit switch, 1 positive limit
/// switch, 2 home switch, 16–31 manufacturer-specific).
pub const DIGITAL_INPUTS: u16 = 0x60FD;

/// CiA 406: position value (UNSIGNED32, measuring steps).
pub const POSITION_VALUE: u16 = 0x6004;
/// CiA 406: linear encoder measuring step settings (RECORD: 1 position step in nm,
/// 2 speed step).
pub const MEASURING_STEP: u16 = 0x6005;
/// CiA 406: speed value (ARRAY of INTEGER16; sub 1 = channel 1).
pub const SPEED_VALUE: u16 = 0x6030;

/// CiA 402 homing mode, the value of 0x6060 while a drive homes.
pub const MODE_HOMING: i8 = 6;
/// CiA 402 cyclic synchronous velocity mode, the value of 0x6060 the master writes.
pub const MODE_CSV: i8 = 9;
/// Device profile number of drives (low word of 0x1000).
pub const PROFILE_DRIVE: u16 = 402;
/// Device profile number of encoders (low word of 0x1000).
pub const PROFILE_ENCODER: u16 = 406;
