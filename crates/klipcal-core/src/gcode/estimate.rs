//! PURE: print-time estimate of a move sequence with Klipper's look-ahead model — trapezoid
//! moves at one acceleration, junction speeds from square_corner_velocity (junction
//! deviation, toolhead.py `calc_junction`), full stops at extruder-only and Z moves.
//! Numbers in, seconds out; no G-code text here.

/// One XY move of a chain.
#[derive(Debug, Clone, Copy)]
struct Leg {
    /// Unit direction.
    dir: [f64; 2],
    len_mm: f64,
    max_v2: f64,
}

/// Accumulates moves and sums their planned time.
#[derive(Debug, Clone)]
pub struct Planner {
    accel_mm_s2: f64,
    junction_deviation_mm: f64,
    chain: Vec<Leg>,
    total_s: f64,
}

/// Time of a trapezoid move from `v0²` to `v1²` with cruise speed² `vc2`.
fn trapezoid_s(len_mm: f64, v0_2: f64, v1_2: f64, vc2: f64, a: f64) -> f64 {
    let peak2 = (v0_2 + v1_2) / 2.0 + a * len_mm;
    let (v0, v1) = (v0_2.sqrt(), v1_2.sqrt());
    if peak2 > vc2 {
        let vc = vc2.sqrt();
        let ramps_mm = (2.0 * vc2 - v0_2 - v1_2) / (2.0 * a);
        (vc - v0) / a + (vc - v1) / a + (len_mm - ramps_mm).max(0.0) / vc
    } else {
        let vp = peak2.sqrt();
        (vp - v0) / a + (vp - v1) / a
    }
}

impl Planner {
    /// A planner at `accel_mm_s2` with Klipper's `square_corner_velocity`.
    pub fn new(accel_mm_s2: f64, square_corner_velocity_mm_s: f64) -> Self {
        Self {
            accel_mm_s2,
            junction_deviation_mm: square_corner_velocity_mm_s.powi(2)
                * (std::f64::consts::SQRT_2 - 1.0)
                / accel_mm_s2,
            chain: Vec::new(),
            total_s: 0.0,
        }
    }

    /// An XY move of `d` mm at up to `speed_mm_s`.
    pub fn xy(&mut self, d: [f64; 2], speed_mm_s: f64) {
        let len_mm = d[0].hypot(d[1]);
        if len_mm < 1e-12 {
            return;
        }
        self.chain.push(Leg {
            dir: [d[0] / len_mm, d[1] / len_mm],
            len_mm,
            max_v2: speed_mm_s * speed_mm_s,
        });
    }

    /// Something that stops the toolhead (extruder-only or Z move, dwell) and takes `t_s`.
    pub fn stop(&mut self, t_s: f64) {
        self.flush();
        self.total_s += t_s;
    }

    /// Total planned time so far, s.
    pub fn total_s(&mut self) -> f64 {
        self.flush();
        self.total_s
    }

    /// Largest speed² at the junction between legs `prev` and `next` (toolhead.py).
    fn junction_v2(&self, prev: &Leg, next: &Leg) -> f64 {
        let cos_theta = -(prev.dir[0] * next.dir[0] + prev.dir[1] * next.dir[1]);
        let sin_d2 = (0.5 * (1.0 - cos_theta)).max(0.0).sqrt();
        let cos_d2 = (0.5 * (1.0 + cos_theta)).max(0.0).sqrt();
        let mut v2 = prev.max_v2.min(next.max_v2);
        if 1.0 - sin_d2 > 0.0 && cos_d2 > 0.0 {
            let r_jd = sin_d2 / (1.0 - sin_d2);
            let jd_v2 = r_jd * self.junction_deviation_mm * self.accel_mm_s2;
            let quarter_tan = 0.25 * sin_d2 / cos_d2;
            let a2 = 2.0 * self.accel_mm_s2;
            v2 = v2
                .min(jd_v2)
                .min(a2 * next.len_mm * quarter_tan)
                .min(a2 * prev.len_mm * quarter_tan);
        }
        v2
    }

    fn flush(&mut self) {
        let n = self.chain.len();
        if n == 0 {
            return;
        }
        let a = self.accel_mm_s2;
        // junction caps: start of leg i; the chain starts and ends at rest
        let mut cap = Vec::with_capacity(n + 1);
        cap.push(0.0);
        cap.extend(
            self.chain
                .windows(2)
                .map(|w| self.junction_v2(&w[0], &w[1])),
        );
        cap.push(0.0);
        // backward: the most each leg may start with and still slow down in time
        let mut back = cap.clone();
        for i in (0..n).rev() {
            back[i] = back[i].min(back[i + 1] + 2.0 * a * self.chain[i].len_mm);
        }
        // forward: accelerate as allowed, then time each trapezoid
        let mut v0_2 = 0.0_f64;
        for (i, leg) in self.chain.iter().enumerate() {
            let start = v0_2.min(back[i]);
            let end = (start + 2.0 * a * leg.len_mm)
                .min(back[i + 1])
                .min(leg.max_v2);
            self.total_s += trapezoid_s(leg.len_mm, start, end, leg.max_v2, a);
            v0_2 = end;
        }
        self.chain.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_straight_line_cut_into_pieces_takes_as_long_as_one_move() {
        let mut one = Planner::new(800.0, 5.0);
        one.xy([100.0, 0.0], 60.0);
        let mut many = Planner::new(800.0, 5.0);
        for _ in 0..100 {
            many.xy([1.0, 0.0], 60.0);
        }
        let t = 100.0 / 60.0 + 60.0 / 800.0;
        assert!((one.total_s() - t).abs() < 1e-9);
        assert!((many.total_s() - t).abs() < 1e-9);
    }

    #[test]
    fn a_square_corner_is_taken_at_square_corner_velocity() {
        // Klipper docs: square_corner_velocity is the speed through a 90° corner.
        let mut p = Planner::new(800.0, 5.0);
        let prev = Leg {
            dir: [1.0, 0.0],
            len_mm: 100.0,
            max_v2: 3600.0,
        };
        let next = Leg {
            dir: [0.0, 1.0],
            len_mm: 100.0,
            max_v2: 3600.0,
        };
        assert!((p.junction_v2(&prev, &next) - 25.0).abs() < 1e-9);
        p.xy([100.0, 0.0], 60.0);
        p.xy([0.0, 100.0], 60.0);
        let two_stops = 2.0 * (100.0 / 60.0 + 60.0 / 800.0);
        assert!(p.total_s() < two_stops);
    }

    #[test]
    fn a_reversal_stops_the_toolhead() {
        let mut p = Planner::new(800.0, 5.0);
        p.xy([10.0, 0.0], 60.0);
        p.xy([-10.0, 0.0], 60.0);
        let mut q = Planner::new(800.0, 5.0);
        q.xy([10.0, 0.0], 60.0);
        q.stop(0.0);
        q.xy([-10.0, 0.0], 60.0);
        assert!((p.total_s() - q.total_s()).abs() < 1e-9);
    }
}
