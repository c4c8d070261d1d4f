//! State estimation: odometry with its covariance ([`odometry`]).

pub mod odometry;
