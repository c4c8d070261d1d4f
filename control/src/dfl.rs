//! Controller 1: dynamic feedback linearization tracking controller (seed 000, Sect. IV).
