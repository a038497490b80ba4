//! The bed's history at its target, kept in klipcal's store (issue 38 item 6): Moonraker's
//! temperature store holds only its last 20 min, so klipcal reads it once a minute while the
//! bed is heated and merges it into [`BedLog`]. A soak resumed after a restart, or a round
//! started on a bed held at its target since the apply, replays that history instead of
//! starting from 0 %; a coupling identified from a cold heat-up is kept for the next warm
//! start of the same bed ([`CarriedCoupling`]).

use std::time::Duration;

use serde_json::{json, Value};

use super::session::{now_unix, Core};
use crate::calib::soak::carry::{BedLog, CarriedCoupling};
use crate::calib::soak::{Coupling, SoakParams};

/// The store's key of the bed's history.
const LOG_KEY: &str = "soak.bed_log";
/// The store's key of the last identified coupling.
const COUPLING_KEY: &str = "soak.coupling";
/// How often the history is brought up to date at most (well within the 20 min Moonraker
/// keeps by default); more often when Moonraker keeps less (`temperature_store_size`): half
/// of what it keeps, at least every [`RECORD_MIN`].
const RECORD_EVERY: Duration = Duration::from_secs(60);
const RECORD_MIN: Duration = Duration::from_secs(5);

/// One read of Moonraker's temperature store, merged into the history.
pub(crate) struct Read {
    /// The bed's history at its current target, up to now.
    pub log: BedLog,
    /// The store as read (its series end at `now_unix`).
    pub store: Value,
    /// When it was read, Unix s.
    pub now_unix: f64,
}

fn series(entry: &Value, key: &str) -> Vec<f64> {
    entry[key]
        .as_array()
        .map(|a| a.iter().map(|v| v.as_f64().unwrap_or(f64::NAN)).collect())
        .unwrap_or_default()
}

/// Reads the temperature store, merges its bed series into the stored history and saves it.
///
/// # Errors
/// Moonraker unreachable. A history the store cannot keep is logged, not an error.
pub(crate) async fn record(core: &Core, skip_below_c: f64) -> anyhow::Result<Read> {
    let store = core
        .m()
        .call(
            "server.temperature_store",
            json!({"include_monitors": false}),
        )
        .await?;
    let now = now_unix();
    let mut log: BedLog = core
        .store()
        .value(LOG_KEY)
        .ok()
        .flatten()
        .and_then(|v| serde_json::from_value(v).ok())
        .unwrap_or_default();
    let was_empty = log.samples.is_empty();
    let bed = &store["heater_bed"];
    log.merge(
        now,
        &series(bed, "temperatures"),
        &series(bed, "targets"),
        &series(bed, "powers"),
        skip_below_c,
    );
    if !(was_empty && log.samples.is_empty()) {
        let saved = serde_json::to_value(&log)
            .map_err(anyhow::Error::from)
            .and_then(|v| Ok(core.store().set_value(LOG_KEY, &v)?));
        if let Err(e) = saved {
            tracing::warn!(error = %e, "the bed's history was not saved");
        }
    }
    Ok(Read {
        log,
        store,
        now_unix: now,
    })
}

/// Brings the bed's history up to date once a minute (or at half what Moonraker keeps),
/// until shutdown.
pub(crate) async fn recorder(core: Core, skip_below_c: f64) {
    loop {
        // Moonraker not there yet (or gone): tried again soon, so no heat-up is missed.
        let every = match record(&core, skip_below_c).await {
            Ok(read) => {
                let kept_s = series(&read.store["heater_bed"], "temperatures").len() as u64;
                Duration::from_secs(kept_s / 2).clamp(RECORD_MIN, RECORD_EVERY)
            }
            Err(e) => {
                tracing::debug!(error = %e, "bed history not brought up to date");
                RECORD_MIN
            }
        };
        tokio::select! {
            () = core.shutdown().cancelled() => return,
            () = tokio::time::sleep(every) => {}
        }
    }
}

/// Keeps an identified coupling for the next warm start.
pub(crate) fn keep_coupling(core: &Core, coupling: &Coupling, params: &SoakParams) {
    let Some(kept) = CarriedCoupling::of(coupling, params, now_unix()) else {
        return;
    };
    let saved = serde_json::to_value(&kept)
        .map_err(anyhow::Error::from)
        .and_then(|v| Ok(core.store().set_value(COUPLING_KEY, &v)?));
    if let Err(e) = saved {
        tracing::warn!(error = %e, "the identified coupling was not kept");
    }
}

/// The coupling identified earlier for this bed, when it may be used for a warm start now.
pub(crate) fn carried_coupling(core: &Core, params: &SoakParams) -> Option<Coupling> {
    let kept: CarriedCoupling = core
        .store()
        .value(COUPLING_KEY)
        .ok()
        .flatten()
        .and_then(|v| serde_json::from_value(v).ok())?;
    kept.for_warm_start(params, now_unix())
}

/// The chamber reading of the store's `name` series at Unix time `t_unix` (the series ends at
/// `now_unix`, 1 Hz), when the store reaches back that far.
pub(crate) fn chamber_at(store: &Value, name: &str, now_unix: f64, t_unix: f64) -> Option<f64> {
    let temps = store[name]["temperatures"].as_array()?;
    let back = (now_unix - t_unix).round();
    if !(back >= 0.0 && back < temps.len() as f64) {
        return None;
    }
    temps[temps.len() - 1 - back as usize]
        .as_f64()
        .filter(|v| v.is_finite())
}
