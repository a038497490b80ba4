//! The four-node family of `klipcal bench soak` (issue 29): heater pad, aluminium plate, print
//! surface (steel sheet on a magnet, or glass on clips) and the air and frame around the bed
//! (open frame, or an enclosure that warms over hours), in physical units from real materials
//! and sizes (220–400 mm beds, 150–900 W), with the thermistor in the pad or in the plate.
//!
//! Control is Klipper's own, ported line by line from klippy/extras in the bench venv:
//! `heaters.ControlPID.temperature_update` (integral clamp, derivative over `smooth_time`,
//! integral frozen while the output is clamped), `Heater.set_pwm` (updates under 0.05 held up
//! to 0.75 × MAX_HEAT_TIME; the power Klipper reports is the last value set), and the gains come
//! from `pid_calibrate.ControlAutoTune` run on the same bed first (relay between the target and
//! target − 5 °C at max_power, Åström–Hägglund Ku/Tu at the median cycle, Ziegler–Nichols). The
//! thermistor is read every 0.3 s (Klipper's report time) with ADC noise and 0.01 °C rounding.
//!
//! Truth is the surface: its final temperature is the steady state with the thermistor's node
//! held at the target, and a declaration is early when the surface was still more than the
//! budget below it.

use super::soak_noise::{gauss, uniform};

mod judge;
mod kalico;
mod kalico_check;
mod klipper;

pub(crate) use judge::{preset_name, run_bed, BedResult};
pub(crate) use kalico::kalico_python;
pub(crate) use kalico_check::{kalico_check, CAL_TOL};
pub(crate) use klipper::{klipper_check, klippy_python, GAIN_TOL, PWM_TOL};

/// One bed: nodes pad, plate, surface, air; conductances W/K; capacities J/K.
#[derive(Debug, Clone)]
pub(crate) struct FourNode {
    /// What it is, for the report.
    pub kind: Kind,
    c: [f64; 4],
    k_pad_plate: f64,
    k_plate_surf: f64,
    h_surf_air: f64,
    h_pad_air: f64,
    h_air_room: f64,
    p_max_w: f64,
    room_c: f64,
    /// Target, °C.
    pub target_c: f64,
    /// ADC noise, °C (sd).
    pub noise_c: f64,
}

/// The bed's control: Klipper's PID (gains from PID_CALIBRATE) or Kalico's MPC (its profile
/// from MPC_CALIBRATE).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Control {
    /// Klipper's `control: pid`.
    Pid,
    /// Kalico's `control: mpc`.
    Mpc,
}

impl Control {
    /// Its name in the report.
    #[must_use]
    pub(crate) fn name(self) -> &'static str {
        match self {
            Control::Pid => "Klipper's PID",
            Control::Mpc => "Kalico's MPC",
        }
    }
}

/// A family of four-node beds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Kind {
    /// Glass on clips (else a steel sheet on a magnet).
    pub glass: bool,
    /// Thermistor in the pad (else in the plate).
    pub pad_sensed: bool,
    /// Enclosed (else open frame).
    pub enclosed: bool,
    /// An enclosure whose air and frame warm for hours (time constant 1.7–5.6 h, beyond
    /// `tau_max_s`): only a chamber thermometer can show it.
    pub slow_air: bool,
}

impl Kind {
    /// Its name in the report.
    #[must_use]
    pub(crate) fn name(&self) -> String {
        format!(
            "{} {}, thermistor in the {}",
            if self.enclosed {
                "enclosed"
            } else {
                "open-frame"
            },
            if self.glass {
                "glass on clips"
            } else {
                "steel on magnet"
            },
            if self.pad_sensed { "pad" } else { "plate" }
        ) + if self.slow_air {
            ", air warming for hours"
        } else {
            ""
        }
    }

    /// Glass on a pad-sensed plate in an enclosure whose air warms for hours (issue 38: declared
    /// while its surface still had more than 1 K to go without a chamber thermometer).
    #[must_use]
    pub(crate) fn slow_enclosure() -> Kind {
        Kind {
            glass: true,
            pad_sensed: true,
            enclosed: true,
            slow_air: true,
        }
    }

    /// All eight.
    #[must_use]
    pub(crate) fn all() -> Vec<Kind> {
        let mut v = Vec::new();
        for enclosed in [false, true] {
            for glass in [false, true] {
                for pad_sensed in [false, true] {
                    v.push(Kind {
                        glass,
                        pad_sensed,
                        enclosed,
                        slow_air: false,
                    });
                }
            }
        }
        v
    }
}

/// The grid's knobs, each 0..1 within its physical range (coupling, plate thickness,
/// enclosure time constant, noise), or drawn at random.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Knobs {
    /// Surface contact (0 poor, 1 good).
    pub coupling: f64,
    /// Plate thickness (0 thin, 1 thick).
    pub plate: f64,
    /// Enclosure air+frame heat capacity (0 small, 1 large).
    pub enclosure: f64,
    /// ADC noise (0 quiet, 1 noisy).
    pub noise: f64,
}

impl FourNode {
    /// A bed of `kind` from the knobs, with the rest drawn.
    #[must_use]
    pub(crate) fn new(kind: Kind, k: Knobs, rng: &mut fastrand::Rng) -> Self {
        let side = uniform(rng, 0.22, 0.40);
        let a = side * side;
        // Heater: 0.35–1 W/cm², within 150–900 W.
        let p_max_w = (a * uniform(rng, 3500.0, 10_000.0)).clamp(150.0, 900.0);
        // Silicone pad 1.5 mm (1.2 g/cm³, 1.3 J/gK); plate 3–8 mm aluminium (2.7, 0.9).
        let c_pad = a * 0.0015 * 1200.0 * 1300.0;
        let t_plate = 0.003 + 0.005 * k.plate;
        let c_plate = a * t_plate * 2700.0 * 900.0;
        // The pad's thermistor sits in silicone (0.3 W/mK) about 0.5–1 mm from the plate.
        let k_pad_plate = a * 0.3 / uniform(rng, 0.0005, 0.001);
        let (c_surf, k_plate_surf) = if kind.glass {
            // 3–4 mm borosilicate (2.23 g/cm³, 0.83 J/gK, 1.1 W/mK) on clips over an air gap of
            // 0.05–0.4 mm (0.03 W/mK).
            let t = uniform(rng, 0.003, 0.004);
            let gap = 0.0004 - 0.00035 * k.coupling;
            let u = 1.0 / (gap / 0.03 + t / 2.0 / 1.1);
            (a * t * 2230.0 * 830.0, a * u)
        } else {
            // 0.5 mm spring steel (7.85, 0.46) with PEI on a 1 mm magnetic sheet (3.6, 0.9,
            // 0.4–1.2 W/mK).
            let c = a * (0.0005 * 7850.0 * 460.0 + 0.001 * 3600.0 * 0.9e3);
            let km = 0.4 + 0.8 * k.coupling;
            (c, a / (0.001 / km + 0.0005 / 20.0))
        };
        // Surface to air: convection 5–9 W/m²K and radiation (ε 0.9, ~7 W/m²K at 60–100 °C);
        // the pad's underside 2–8 W/m²K (insulated or not).
        let h_surf_air = a * uniform(rng, 12.0, 16.0);
        let h_pad_air = a * uniform(rng, 2.0, 8.0);
        // Air and frame: open frame, a small mass well coupled to the room (minutes, a degree
        // or two); enclosed, the air, extrusions and panels (12–40 kJ/K: ~5 kg of aluminium
        // frame, ~5 kg of panels) behind 1.5–3 m² of acrylic or polycarbonate panels at
        // 4–6 W/m²K (6–18 W/K): from about 10 min to 2 h.
        let (c_air, h_air_room) = if kind.slow_air {
            // An enclosure that warms for hours: a heavy frame and panels (60–120 kJ/K) behind
            // well-insulated walls (6–10 W/K).
            (60_000.0 + 60_000.0 * k.enclosure, uniform(rng, 6.0, 10.0))
        } else if kind.enclosed {
            (12_000.0 + 28_000.0 * k.enclosure, uniform(rng, 6.0, 18.0))
        } else {
            (2_000.0 + 3_000.0 * k.enclosure, uniform(rng, 30.0, 80.0))
        };
        FourNode {
            kind,
            c: [c_pad, c_plate, c_surf, c_air],
            k_pad_plate,
            k_plate_surf,
            h_surf_air,
            h_pad_air,
            h_air_room,
            p_max_w,
            room_c: uniform(rng, 18.0, 26.0),
            target_c: if kind.glass {
                uniform(rng, 55.0, 75.0)
            } else {
                uniform(rng, 55.0, 100.0)
            },
            // Klipper averages 8 ADC samples a report: 0.01–0.05 °C of noise on a bed.
            noise_c: 0.01 + 0.04 * k.noise,
        }
    }

    /// A random bed of `kind`.
    #[must_use]
    pub(crate) fn random(kind: Kind, rng: &mut fastrand::Rng) -> Self {
        let k = Knobs {
            coupling: rng.f64(),
            plate: rng.f64(),
            enclosure: rng.f64(),
            noise: rng.f64(),
        };
        Self::new(kind, k, rng)
    }

    fn sensor_node(&self) -> usize {
        usize::from(!self.kind.pad_sensed)
    }

    /// The true coupling from the thermistor's node to the surface, full power per K.
    #[must_use]
    pub(crate) fn g_true(&self) -> f64 {
        let w = if self.kind.pad_sensed {
            1.0 / (1.0 / self.k_pad_plate + 1.0 / self.k_plate_surf)
        } else {
            self.k_plate_surf
        };
        w / self.p_max_w
    }

    /// The time constants of the bed with the thermistor's node held (and the heater's power
    /// free): the modes the power decays with and the surface relaxes with, s, slowest first.
    #[must_use]
    pub(crate) fn clamped_taus_s(&self) -> Vec<f64> {
        let s = self.sensor_node();
        let k = |i: usize, j: usize| -> f64 {
            match (i.min(j), i.max(j)) {
                (0, 1) => self.k_pad_plate,
                (1, 2) => self.k_plate_surf,
                (2, 3) => self.h_surf_air,
                (0, 3) => self.h_pad_air,
                _ => 0.0,
            }
        };
        let free: Vec<usize> = (0..4).filter(|i| *i != s).collect();
        // Symmetric form C^-1/2 K C^-1/2 of the conductance matrix over the free nodes (the
        // held node and the room are fixed: their conductances sit on the diagonal).
        let m = nalgebra::DMatrix::from_fn(free.len(), free.len(), |a, b| {
            let (i, j) = (free[a], free[b]);
            let kij = if i == j {
                (0..4).map(|n| k(i, n)).sum::<f64>() + if i == 3 { self.h_air_room } else { 0.0 }
            } else {
                -k(i, j)
            };
            kij / (self.c[i] * self.c[j]).sqrt()
        });
        let mut taus: Vec<f64> = m
            .symmetric_eigen()
            .eigenvalues
            .iter()
            .map(|l| 1.0 / l)
            .collect();
        taus.sort_by(|a, b| b.total_cmp(a));
        taus
    }

    /// Heat flows into each node at temperatures `t` and heater power `p` (W).
    fn flows(&self, t: &[f64; 4], p_w: f64) -> [f64; 4] {
        let q_pp = self.k_pad_plate * (t[0] - t[1]);
        let q_ps = self.k_plate_surf * (t[1] - t[2]);
        let q_sa = self.h_surf_air * (t[2] - t[3]);
        let q_pa = self.h_pad_air * (t[0] - t[3]);
        let q_ar = self.h_air_room * (t[3] - self.room_c);
        [
            p_w - q_pp - q_pa,
            q_pp - q_ps,
            q_ps - q_sa,
            q_sa + q_pa - q_ar,
        ]
    }

    /// The surface's final temperature with the thermistor's node held at the target: the
    /// other three nodes' steady state (Gauss–Seidel on the linear balance).
    #[must_use]
    pub(crate) fn surface_final_c(&self) -> f64 {
        let s = self.sensor_node();
        let mut t = [self.target_c; 4];
        t[3] = self.room_c;
        for _ in 0..20_000 {
            // Each free node at the conductance-weighted mean of its neighbours.
            if s == 0 {
                t[1] = (self.k_pad_plate * t[0] + self.k_plate_surf * t[2])
                    / (self.k_pad_plate + self.k_plate_surf);
            } else {
                // The plate held: the pad runs hotter by what the plate passes on.
                t[0] = t[1] + self.k_plate_surf * (t[1] - t[2]) / self.k_pad_plate;
            }
            t[2] = (self.k_plate_surf * t[1] + self.h_surf_air * t[3])
                / (self.k_plate_surf + self.h_surf_air);
            t[3] = (self.h_surf_air * t[2] + self.h_pad_air * t[0] + self.h_air_room * self.room_c)
                / (self.h_surf_air + self.h_pad_air + self.h_air_room);
        }
        t[2]
    }
}

/// The thermistor's reading: ADC noise and Klipper's 0.01 °C.
fn read(bed: &FourNode, t: &[f64; 4], rng: &mut fastrand::Rng) -> f64 {
    let raw = t[bed.sensor_node()] + bed.noise_c * gauss(rng);
    (raw * 100.0).round() / 100.0
}

/// Steps the plant by `dt` at power fraction `p`.
fn step(bed: &FourNode, t: &mut [f64; 4], p: f64, dt: f64) {
    // Sub-steps keep explicit Euler stable on the fast pad and surface.
    let n = 3;
    let h = dt / f64::from(n);
    for _ in 0..n {
        let f = bed.flows(t, p * bed.p_max_w);
        for i in 0..4 {
            t[i] += h * f[i] / bed.c[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// soak.frame = "open" rules out decays up to `OPEN_FRAME_TAU_MAX_S`: every open-frame
    /// bed of this family, at every corner of the knobs, settles within it; the enclosed ones
    /// do not all (which is why the setting is not the default).
    #[test]
    fn open_frame_beds_have_their_slowest_clamped_mode_within_the_open_frame_bound() {
        let mut rng = fastrand::Rng::with_seed(11);
        let (mut open_max, mut enclosed_max) = (0.0f64, 0.0f64);
        for kind in Kind::all() {
            for corner in 0..16u32 {
                let f = |b: u32| f64::from((corner >> b) & 1);
                let knobs = Knobs {
                    coupling: f(0),
                    plate: f(1),
                    enclosure: f(2),
                    noise: f(3),
                };
                for _ in 0..8 {
                    let bed = FourNode::new(kind, knobs, &mut rng);
                    let slowest = bed.clamped_taus_s()[0];
                    if kind.enclosed {
                        enclosed_max = enclosed_max.max(slowest);
                    } else {
                        open_max = open_max.max(slowest);
                    }
                }
            }
        }
        assert!(
            open_max <= crate::calib::soak::OPEN_FRAME_TAU_MAX_S,
            "open frame: slowest clamped mode {open_max} s"
        );
        assert!(
            enclosed_max > crate::calib::soak::OPEN_FRAME_TAU_MAX_S,
            "enclosed: {enclosed_max} s"
        );
    }

    /// The presets are the weak end of their builds: every bed of this family (random, and at
    /// every corner of the knobs) has a coupling at or above its kind's preset and a stack
    /// time R·C within the preset's, so neither bound the identification uses is above the
    /// true G. (Before, the presets held typical values: 1/30 for steel-pad was above the true
    /// G of 9 of 24 open-frame beds, 1/150 above one open glass-pad bed.)
    #[test]
    fn every_bed_of_the_family_is_within_its_presets_physical_bounds() {
        let mut rng = fastrand::Rng::with_seed(21);
        for kind in Kind::all() {
            let p = crate::calib::soak::BED_PRESETS
                .iter()
                .find(|b| b.name == preset_name(kind))
                .unwrap();
            for i in 0..400u32 {
                let bed = if i < 16 {
                    let f = |b: u32| f64::from((i >> b) & 1);
                    let knobs = Knobs {
                        coupling: f(0),
                        plate: f(1),
                        enclosure: f(2),
                        noise: f(3),
                    };
                    FourNode::new(kind, knobs, &mut rng)
                } else {
                    FourNode::random(kind, &mut rng)
                };
                let g = bed.g_true();
                let rc = (bed.c[0] + bed.c[1] + bed.c[2]) / bed.p_max_w / g;
                assert!(
                    g >= p.g,
                    "{}: G 1/{:.0} below the preset's 1/{:.0}",
                    kind.name(),
                    1.0 / g,
                    1.0 / p.g
                );
                assert!(
                    rc <= p.rc_s,
                    "{}: R·C {rc:.0} s over the preset's {:.0}",
                    kind.name(),
                    p.rc_s
                );
            }
        }
    }
}
