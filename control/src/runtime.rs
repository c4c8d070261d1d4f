//! The 250 Hz cycle: sans-IO cycle core, lockstep driver and real-time cycle thread.
