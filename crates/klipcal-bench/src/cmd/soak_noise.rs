//! The random draws the soak benchmarks share (`soak_bench`, `soak_families`,
//! `soak_four_node`), kept apart so those modules do not import each other in a circle.

/// A uniform draw in `[lo, hi)`.
pub(crate) fn uniform(rng: &mut fastrand::Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.f64()
}

/// A standard normal draw (Box–Muller).
pub(crate) fn gauss(rng: &mut fastrand::Rng) -> f64 {
    // Box–Muller; 1 − f64() is in (0, 1].
    let u = 1.0 - rng.f64();
    let v = rng.f64();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}
