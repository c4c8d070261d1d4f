//! Reference trajectories: quasi-trapezoidal profiles with parabolic blends, quintic segments through waypoints.
