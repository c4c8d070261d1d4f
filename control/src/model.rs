//! Seed 000 kinematic model of a platform with steered wheels on movable legs (eqs. 17–22), ICR.
