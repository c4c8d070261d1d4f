//! Controller 2: kinematic tracking with per-wheel inverse kinematics and whole-platform desaturation.
