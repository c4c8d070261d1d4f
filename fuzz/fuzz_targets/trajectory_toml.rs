//! Fuzz target: the waypoint trajectory parser (`QuinticSpline::from_toml_str`) against the
//! default platform.
//!
//! Any input must give `Ok` or an error, never a panic. A trajectory that is accepted must
//! have a finite, non-negative duration and give finite reference samples (z*, ż*, z̈*, z⃛*)
//! with legs inside their range at a spread of times inside and outside [0, duration]: the
//! controller must never receive a non-finite reference from an accepted file.
//!
//! Run: `cargo +nightly fuzz run trajectory_toml` from the repository root.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rollbase_control::reference::trajectory::{QuinticSpline, Trajectory};
use rollbase_control::Platform;

fuzz_target!(|input: &[u8]| {
    let Ok(text) = std::str::from_utf8(input) else {
        return;
    };
    let p = Platform::justin();
    let Ok(traj) = QuinticSpline::from_toml_str(&p, text) else {
        return;
    };
    let d = traj.duration();
    assert!(d.is_finite() && d >= 0.0, "duration {d}");
    for k in -2..=34 {
        let t = d * f64::from(k) / 32.0;
        let s = traj.sample(t);
        assert!(s.z.iter().all(|v| v.is_finite()), "z* at t = {t}: {:?}", s.z);
        assert!(s.dz.iter().all(|v| v.is_finite()), "dz* at t = {t}");
        assert!(s.ddz.iter().all(|v| v.is_finite()), "ddz* at t = {t}");
        assert!(s.dddz.iter().all(|v| v.is_finite()), "dddz* at t = {t}");
        for (i, w) in p.wheels.iter().enumerate() {
            let l = s.z[3 + i];
            assert!(
                l >= w.lambda_min - 1e-6 && l <= w.lambda_max + 1e-6,
                "leg {i} = {l} outside [{}, {}] at t = {t}",
                w.lambda_min,
                w.lambda_max
            );
        }
    }
});
