//! Supervisor state machine: Idle, Aligning, Tracking, Stopping, Stopped and Fault.
