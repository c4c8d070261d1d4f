//! Least-squares odometry from wheel measurements with exact SE(2) integration and a slip residual.
