//! Singularity avoidance (seed 001): ICR potential fields, leg repulsion and the return loop.
