//! PURE: what a soak already did, carried over (issue 38 item 6). Moonraker's temperature store
//! keeps only its last `temperature_store_size` seconds (20 min by default): a soak resumed
//! after a restart of klipcal, or a round started on a bed held at its target since the apply,
//! would otherwise see a bed already in its band with no heat-up and start again from 0 %.
//! [`BedLog`] is the bed's samples since its target was set, merged from successive reads of
//! the store (older ones thinned to [`THIN_BLOCK_S`] blocks) and refused where the reads
//! leave a gap, so that a replay of it is the bed's real history at this target or nothing.
//! [`CarriedCoupling`] is a coupling identified from an earlier cold heat-up of the same bed,
//! for a later warm start (the bed reheated after Klipper's restart by an apply).

use serde::{Deserialize, Serialize};

use super::{Coupling, CouplingSource, SoakParams};

/// Samples older than this (s before the newest) are thinned to one per [`THIN_BLOCK_S`].
pub const THIN_AFTER_S: f64 = 1200.0;
/// The block older samples are averaged over, s (the detector's default bin).
pub const THIN_BLOCK_S: f64 = 10.0;
/// The longest history kept, s (a soak longer than this is far past any limit).
pub const LOG_MAX_S: f64 = 12.0 * 3600.0;
/// Two reads further apart than this beyond what the store holds leave a gap: what came
/// before it is not known to be this stretch at the target, and is dropped.
pub const GAP_S: f64 = 30.0;
/// A coupling identified longer ago than this is not carried over (a sheet may have been
/// swapped since).
pub const CARRY_MAX_AGE_S: f64 = 6.0 * 3600.0;

/// One sample: Unix time, power (0..1), temperature and target, °C.
pub type LogSample = [f64; 4];

/// The bed since its current target was set, as far as klipcal saw it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BedLog {
    /// Oldest first, one per second (the last [`THIN_AFTER_S`]) or per [`THIN_BLOCK_S`].
    pub samples: Vec<LogSample>,
}

impl BedLog {
    /// Merges one read of the temperature store: its heater_bed series (1 Hz, the last entry
    /// at `now_unix`). Keeps only the stretch at the newest target; an unheated bed (target at
    /// or below `skip_below_c`) leaves nothing. A read that does not reach back to the log's
    /// last sample (klipcal was away longer than the store holds) drops what came before it.
    pub fn merge(
        &mut self,
        now_unix: f64,
        temps: &[f64],
        targets: &[f64],
        powers: &[f64],
        skip_below_c: f64,
    ) {
        let n = temps.len().min(targets.len()).min(powers.len());
        if n == 0 || !now_unix.is_finite() {
            return;
        }
        let at = |i: usize| now_unix - (n - 1 - i) as f64;
        let last_logged = self.samples.last().map(|s| s[0]);
        if last_logged.map_or(true, |t| at(0) > t + GAP_S) || last_logged > Some(now_unix + 1.0) {
            // Nothing to join to (or a clock that went back): the read stands alone.
            self.samples.clear();
        }
        let after = self
            .samples
            .last()
            .map_or(f64::NEG_INFINITY, |s| s[0] + 0.5);
        for i in 0..n {
            let s = [at(i), powers[i], temps[i], targets[i]];
            if s[0] > after && s.iter().all(|v| v.is_finite()) {
                self.samples.push(s);
            }
        }
        self.keep_current_target(skip_below_c);
        self.thin(now_unix);
    }

    /// Drops everything before the newest target (and all of it for an unheated bed).
    fn keep_current_target(&mut self, skip_below_c: f64) {
        let Some(last) = self.samples.last().map(|s| s[3]) else {
            return;
        };
        if last <= skip_below_c {
            self.samples.clear();
            return;
        }
        let from = self
            .samples
            .iter()
            .rposition(|s| (s[3] - last).abs() >= 0.05)
            .map_or(0, |i| i + 1);
        self.samples.drain(..from);
    }

    /// Averages the samples older than [`THIN_AFTER_S`] over [`THIN_BLOCK_S`] blocks (the
    /// power's mean, the last temperature) and drops those beyond [`LOG_MAX_S`].
    fn thin(&mut self, now_unix: f64) {
        let old_before = now_unix - THIN_AFTER_S;
        let split = self.samples.partition_point(|s| s[0] < old_before);
        let (old, recent) = self.samples.split_at(split);
        let mut out: Vec<LogSample> = Vec::with_capacity(old.len() / 4 + recent.len());
        let mut i = 0;
        while i < old.len() {
            let start = old[i][0];
            let mut j = i;
            while j < old.len() && old[j][0] < start + THIN_BLOCK_S - 0.25 {
                j += 1;
            }
            let block = &old[i..j.max(i + 1)];
            let power = block.iter().map(|s| s[1]).sum::<f64>() / block.len() as f64;
            let end = block[block.len() - 1];
            out.push([start, power, end[2], end[3]]);
            i = j.max(i + 1);
        }
        out.extend_from_slice(recent);
        let keep_from = now_unix - LOG_MAX_S;
        out.retain(|s| s[0] >= keep_from);
        self.samples = out;
    }

    /// The samples at `target_c` (within 0.5 °C), oldest first, or none when the log's target
    /// is another one.
    #[must_use]
    pub fn at_target(&self, target_c: f64) -> &[LogSample] {
        match self.samples.last() {
            Some(s) if (s[3] - target_c).abs() < 0.5 => &self.samples,
            _ => &[],
        }
    }
}

/// A coupling identified from a cold heat-up, kept for the next warm start of the same bed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CarriedCoupling {
    /// `soak.bed` it was identified for (its build's bounds are in it).
    pub bed: String,
    /// G used (the low end), its interval, the stack's charge time, full power per K and s.
    pub g: f64,
    /// Low end of the interval.
    pub low: f64,
    /// High end of the interval (infinite: not bounded).
    pub high: Option<f64>,
    /// The stack's charge time, s.
    pub charge_s: f64,
    /// The bed's heat capacity, full power·s/K, when identified.
    pub heat_capacity: Option<f64>,
    /// When it was identified, Unix s.
    pub at_unix: f64,
}

impl CarriedCoupling {
    /// What to keep of `c`, identified at `at_unix` with `params`: only an identified coupling.
    #[must_use]
    pub fn of(c: &Coupling, params: &SoakParams, at_unix: f64) -> Option<Self> {
        (c.source == CouplingSource::Identified).then(|| CarriedCoupling {
            bed: params.bed.clone(),
            g: c.g,
            low: c.low,
            high: c.high.is_finite().then_some(c.high),
            charge_s: c.charge_s,
            heat_capacity: c.heat_capacity,
            at_unix,
        })
    }

    /// The coupling for a warm start at `now_unix` with `params`: when it was identified for
    /// the same `soak.bed`, within [`CARRY_MAX_AGE_S`], and its numbers are sane.
    #[must_use]
    pub fn for_warm_start(&self, params: &SoakParams, now_unix: f64) -> Option<Coupling> {
        let age = now_unix - self.at_unix;
        let sane = self.g.is_finite()
            && self.g > 0.0
            && self.low.is_finite()
            && self.low > 0.0
            && self.g <= self.high.unwrap_or(f64::INFINITY)
            && self.charge_s.is_finite()
            && self.charge_s >= 0.0;
        (self.bed == params.bed && (0.0..=CARRY_MAX_AGE_S).contains(&age) && sane).then(|| {
            Coupling {
                g: self.g,
                low: self.low,
                high: self.high.unwrap_or(f64::INFINITY),
                charge_s: self.charge_s,
                source: CouplingSource::Identified,
                heat_capacity: self.heat_capacity,
                why: format!(
                    "G identified from this bed's cold heat-up {:.0} min ago: 1/{:.0} of full \
                     power per K (the low end), carried over to this warm start",
                    age / 60.0,
                    1.0 / self.g
                ),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(n: usize, target: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        (vec![target; n], vec![target; n], vec![0.3; n])
    }

    #[test]
    fn successive_reads_join_into_one_history_thinned_when_old() {
        let mut log = BedLog::default();
        let (t, g, p) = read(1200, 60.0);
        log.merge(10_000.0, &t, &g, &p, 30.0);
        assert_eq!(log.samples.len(), 1200);
        // A minute later: 60 new samples joined, the oldest now thinned.
        log.merge(10_060.0, &t, &g, &p, 30.0);
        let first = log.samples[0][0];
        assert!((first - (10_000.0 - 1199.0)).abs() < 1e-9, "{first}");
        assert_eq!(log.samples.last().unwrap()[0], 10_060.0);
        let old = log
            .samples
            .iter()
            .filter(|s| s[0] < 10_060.0 - THIN_AFTER_S)
            .count();
        assert_eq!(old, 6, "60 s of old samples in 10 s blocks");
        assert_eq!(log.at_target(60.2).len(), log.samples.len());
        assert!(log.at_target(70.0).is_empty());
    }

    #[test]
    fn a_gap_longer_than_the_store_or_a_new_target_drops_the_past() {
        let mut log = BedLog::default();
        let (t, g, p) = read(1200, 60.0);
        log.merge(10_000.0, &t, &g, &p, 30.0);
        // klipcal away for an hour: the store no longer reaches back.
        log.merge(13_600.0, &t, &g, &p, 30.0);
        assert_eq!(log.samples[0][0], 13_600.0 - 1199.0);
        // A new target 30 s ago, in the read a minute later (the store's past is what the
        // last read saw): only the stretch at it is kept.
        let mut g2 = g.clone();
        for v in &mut g2[1170..] {
            *v = 80.0;
        }
        log.merge(13_660.0, &t, &g2, &p, 30.0);
        assert!(log.samples.iter().all(|s| s[3] == 80.0));
        assert_eq!(log.samples.len(), 30);
        // The bed turned off: nothing to carry.
        log.merge(13_720.0, &t, &vec![0.0; 1200], &p, 30.0);
        assert!(log.samples.is_empty());
    }

    #[test]
    fn a_coupling_is_carried_only_for_the_same_bed_and_not_too_old() {
        let params = SoakParams {
            bed: "steel-pad".into(),
            ..SoakParams::default()
        };
        let c = Coupling {
            g: 0.02,
            low: 0.02,
            high: 0.03,
            charge_s: 60.0,
            source: CouplingSource::Identified,
            why: String::new(),
            heat_capacity: Some(5.0),
        };
        let kept = CarriedCoupling::of(&c, &params, 1000.0).unwrap();
        let back = kept.for_warm_start(&params, 1000.0 + 600.0).unwrap();
        assert_eq!((back.g, back.low, back.high), (0.02, 0.02, 0.03));
        assert!(back.why.contains("10 min ago"), "{}", back.why);
        assert!(kept
            .for_warm_start(&params, 1000.0 + CARRY_MAX_AGE_S + 1.0)
            .is_none());
        let other = SoakParams::default();
        assert!(kept.for_warm_start(&other, 1600.0).is_none());
        let fallback = Coupling::fallback(&params, "x");
        assert!(CarriedCoupling::of(&fallback, &params, 1000.0).is_none());
    }
}

#[cfg(test)]
mod detector_tests {
    use super::*;
    use crate::calib::soak::test_beds::{run_bed, two_node_bed};

    /// A bed heated from cold identifies its coupling; the same bed reheated warm (after an
    /// apply) uses that coupling instead of the weakest, and so ends no later.
    #[test]
    fn a_warm_start_uses_the_coupling_of_the_beds_earlier_cold_heat_up() {
        let params = SoakParams::default();
        let bed = two_node_bed(0.05, 0.4, 6.0, 0.002, 0.012, 0.03, 3.0 * 3600.0, 5);
        let (cold, _) = run_bed(params.clone(), &bed, 0);
        let identified = cold.coupling().clone();
        assert_eq!(
            identified.source,
            CouplingSource::Identified,
            "{}",
            identified.why
        );
        let kept = CarriedCoupling::of(&identified, &params, 0.0).unwrap();
        // The same bed first seen half-way up (a warm start): its heat-up does not identify.
        let from = bed.iter().position(|s| s[2] > 45.0).unwrap();
        let (warm, warm_at) = run_bed(params.clone(), &bed, from);
        assert_ne!(warm.coupling().source, CouplingSource::Identified);
        let mut d = crate::calib::soak::SoakDetector::new(params.clone());
        d.carry_coupling(kept.for_warm_start(&params, 600.0).unwrap());
        let mut carried_at = None;
        for s in &bed[from..] {
            if let crate::calib::soak::SoakStatus::Stable { at_s } =
                d.push(s[0], s[1], s[2], crate::calib::soak::test_beds::TARGET_C)
            {
                carried_at = Some(at_s);
                break;
            }
        }
        assert_eq!(d.coupling().g, identified.g, "{}", d.coupling().why);
        assert!(
            d.coupling().why.contains("carried over"),
            "{}",
            d.coupling().why
        );
        let (c, w) = (carried_at.unwrap(), warm_at.unwrap_or(f64::INFINITY));
        assert!(c <= w, "carried {c:.0} s, without {w:.0} s");
    }
}
