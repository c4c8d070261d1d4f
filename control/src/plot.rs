//! PNG plots from recordings.
