//! PURE. The frame temperature each probe point of a bed mesh was taken at, from the
//! temperature samples spanning the mesh (Klipper's probe order).

/// The frame temperature of each point of a mesh probed in Klipper's order (rows along Y,
/// alternating direction along X) from temperature samples `(t_s, temp_c)` spanning the
/// mesh: the probes are taken as evenly spread over the samples' time span.
#[must_use]
pub fn point_temps(samples: &[(f64, f64)], x_count: usize, y_count: usize) -> Vec<f64> {
    let n = x_count * y_count;
    let mut out = vec![f64::NAN; n];
    if samples.is_empty() || n == 0 {
        return out;
    }
    let (t0, t1) = (samples[0].0, samples[samples.len() - 1].0);
    let at = |t: f64| -> f64 {
        match samples.iter().position(|s| s.0 >= t) {
            Some(0) => samples[0].1,
            Some(k) => {
                let (a, b) = (samples[k - 1], samples[k]);
                if b.0 > a.0 {
                    a.1 + (b.1 - a.1) * (t - a.0) / (b.0 - a.0)
                } else {
                    b.1
                }
            }
            None => samples[samples.len() - 1].1,
        }
    };
    for y in 0..y_count {
        for x in 0..x_count {
            let order = y * x_count + if y % 2 == 0 { x } else { x_count - 1 - x };
            let frac = if n > 1 {
                order as f64 / (n - 1) as f64
            } else {
                0.0
            };
            out[y * x_count + x] = at(t0 + (t1 - t0) * frac);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_point_gets_the_frame_temperature_of_its_moment_in_klippers_probe_order() {
        // 3×2 mesh probed over 5 s while the frame rose 1 °C/s: row 0 left→right, row 1
        // right→left (Klipper's zigzag).
        let samples: Vec<(f64, f64)> = (0..=5).map(|k| (k as f64, 30.0 + k as f64)).collect();
        let t = point_temps(&samples, 3, 2);
        assert_eq!(t, vec![30.0, 31.0, 32.0, 35.0, 34.0, 33.0]);
        assert!(point_temps(&[], 3, 2).iter().all(|v| v.is_nan()));
    }
}
