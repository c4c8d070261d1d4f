//! Recording of runs as MCAP with JSON schemas.
