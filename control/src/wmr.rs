//! General wheeled-mobile-robot models (seeds 003, 004): wheel types, mobility and steerability, posture and configuration kinematic models.
