//! `[backlash]`: the guided camera measurement's settings and the parameters of its
//! statistics (checked by `calib::backlash` and `calib::backlash_guide`). Each setting is
//! declared once, in the core struct that uses it (`GuideParams`, `BacklashParams`), with its
//! default there; this section flattens them and adds the camera's own two.

use serde::Deserialize;

use crate::calib::backlash::BacklashParams;
use crate::calib::backlash_guide::GuideParams;

/// `[backlash]`: the guided camera measurement and its statistics (seed 004). Read key by key
/// ([`BacklashConfig::from_table`]): each goes to the core struct whose field it is, a value of
/// the wrong type or an unknown key is named.
#[derive(Debug, Clone, PartialEq)]
pub struct BacklashConfig {
    /// The guided procedure's steps and limits: `cycles` (KLIPCAL_BACKLASH_START CYCLES=
    /// overrides), `approach_mm`, `coarse_mm`, `fine_mm`, `small_fine_mm`, `max_travel_mm`,
    /// `plausible_mm`.
    pub guide: GuideParams,
    /// The statistics' thresholds and budgets: `none_needed_max_mm`, `needed_from_mm`,
    /// `compensate_from_mm`, `prior_cycle_sd_mm`, `accel_budget_fraction`, `outlier_sigmas`.
    pub stats: BacklashParams,
    /// The nozzle camera's name in Moonraker's webcam list (KLIPCAL_BACKLASH_CAMERA); empty:
    /// the only webcam there is.
    pub webcam: String,
    /// After a move, wait this long before the first frame (vibration, camera latency), s.
    pub camera_settle_s: f64,
}

/// The camera's own two settings (the rest are the core structs').
#[derive(Debug, Clone, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct Camera {
    webcam: String,
    camera_settle_s: f64,
}

impl Default for Camera {
    fn default() -> Self {
        Camera {
            webcam: String::new(),
            camera_settle_s: 0.3,
        }
    }
}

impl Default for BacklashConfig {
    fn default() -> Self {
        let c = Camera::default();
        BacklashConfig {
            guide: GuideParams::default(),
            stats: BacklashParams::default(),
            webcam: c.webcam,
            camera_settle_s: c.camera_settle_s,
        }
    }
}

/// The core structs' fields that are not settings of `[backlash]`: the guided procedure's
/// reading mode (the benchmark's) and the resolution of readings files' cycles.
const NOT_SETTINGS: [&str; 2] = ["crossing", "jog_resolution_mm"];

/// The fields a struct's derived `Deserialize` reads, as serde declares them (a deserializer
/// that only notes the list `deserialize_struct` is given).
fn fields_of<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    struct Names(Option<&'static [&'static str]>);
    #[derive(Debug)]
    struct Stop;
    impl std::fmt::Display for Stop {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("stop")
        }
    }
    impl std::error::Error for Stop {}
    impl serde::de::Error for Stop {
        fn custom<M: std::fmt::Display>(_: M) -> Self {
            Stop
        }
    }
    impl<'de> serde::Deserializer<'de> for &mut Names {
        type Error = Stop;
        fn deserialize_any<V: serde::de::Visitor<'de>>(self, _: V) -> Result<V::Value, Stop> {
            Err(Stop)
        }
        fn deserialize_struct<V: serde::de::Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Stop> {
            self.0 = Some(fields);
            Err(Stop)
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes
            byte_buf option unit unit_struct newtype_struct seq tuple tuple_struct map enum
            identifier ignored_any
        }
    }
    let mut n = Names(None);
    let _ = T::deserialize(&mut n);
    n.0.unwrap_or(&[])
}

/// Reads `table`'s keys for `T` into `T`, each key alone first so a bad value is named.
fn part<T: serde::de::DeserializeOwned>(table: toml::Table) -> Result<T, String> {
    for (k, v) in &table {
        let one: toml::Table = [(k.clone(), v.clone())].into_iter().collect();
        if let Err(e) = toml::Value::Table(one).try_into::<T>() {
            return Err(format!("backlash.{k}: {e}"));
        }
    }
    toml::Value::Table(table)
        .try_into()
        .map_err(|e| format!("[backlash]: {e}"))
}

impl<'de> Deserialize<'de> for BacklashConfig {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        Self::from_table(toml::Table::deserialize(d)?).map_err(serde::de::Error::custom)
    }
}

impl BacklashConfig {
    /// Every key `[backlash]` takes: the core structs' settings, then the camera's.
    #[must_use]
    pub fn keys() -> Vec<&'static str> {
        fields_of::<GuideParams>()
            .iter()
            .chain(fields_of::<BacklashParams>())
            .chain(fields_of::<Camera>())
            .copied()
            .filter(|k| !NOT_SETTINGS.contains(k))
            .collect()
    }

    /// Reads `[backlash]`: each key into the struct that declares it.
    ///
    /// # Errors
    /// An unknown key (with the keys it takes), or a value of the wrong type, named.
    pub fn from_table(table: toml::Table) -> Result<Self, String> {
        let (guide_keys, stats_keys) = (fields_of::<GuideParams>(), fields_of::<BacklashParams>());
        let (mut guide, mut stats, mut camera) =
            (toml::Table::new(), toml::Table::new(), toml::Table::new());
        for (k, v) in table {
            let to = if NOT_SETTINGS.contains(&k.as_str()) {
                None
            } else if guide_keys.contains(&k.as_str()) {
                Some(&mut guide)
            } else if stats_keys.contains(&k.as_str()) {
                Some(&mut stats)
            } else if fields_of::<Camera>().contains(&k.as_str()) {
                Some(&mut camera)
            } else {
                None
            };
            let Some(to) = to else {
                return Err(format!(
                    "unknown key backlash.{k}; it takes {}",
                    Self::keys().join(", ")
                ));
            };
            to.insert(k, v);
        }
        let camera: Camera = part(camera)?;
        Ok(Self {
            guide: part(guide)?,
            stats: part(stats)?,
            webcam: camera.webcam,
            camera_settle_s: camera.camera_settle_s,
        })
    }

    /// Checks every value is in range.
    ///
    /// # Errors
    /// The first value out of range, named.
    pub(crate) fn validate(&self) -> Result<(), String> {
        self.params()
            .validate()
            .and_then(|()| self.guide().validate())
            .map_err(|e| e.to_string())
    }

    /// The statistics' settings.
    pub fn params(&self) -> BacklashParams {
        BacklashParams {
            // The resolution of cycles that do not say their jog (a readings file: the
            // seed's own jogs, 0.01 mm), not the guided flow's big fine jog.
            jog_resolution_mm: BacklashParams::default().jog_resolution_mm,
            ..self.stats.clone()
        }
    }

    /// The guided procedure's settings.
    pub fn guide(&self) -> GuideParams {
        GuideParams {
            crossing: true,
            ..self.guide.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn every_backlash_setting_reads_into_the_core_struct_that_declares_it() {
        let c = Config::parse(
            "[backlash]\ncycles = 7\nfine_mm = 0.02\ncompensate_from_mm = 0.04\n\
             outlier_sigmas = 5\nwebcam = \"nozzle\"\ncamera_settle_s = 0.5\n",
        )
        .unwrap();
        assert_eq!(c.backlash.guide().cycles, 7);
        assert_eq!(c.backlash.guide().fine_mm, 0.02);
        assert_eq!(c.backlash.params().compensate_from_mm, 0.04);
        assert_eq!(c.backlash.params().outlier_sigmas, 5.0);
        assert_eq!(c.backlash.webcam, "nozzle");
        assert_eq!(c.backlash.camera_settle_s, 0.5);
        // Unset keys keep the core's defaults.
        assert_eq!(
            c.backlash.guide().approach_mm,
            GuideParams::default().approach_mm
        );
    }

    #[test]
    fn an_unknown_or_mistyped_backlash_key_is_named() {
        let e = Config::parse("[backlash]\ncycels = 7\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("backlash.cycels") && e.contains("cycles, approach_mm"),
            "{e}"
        );
        assert_eq!(BacklashConfig::keys().len(), 15);
        let e = Config::parse("[backlash]\ncrossing = false\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("backlash.crossing"), "{e}");
        let e = Config::parse("[backlash]\nfine_mm = \"fine\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("fine_mm"), "{e}");
        let e = Config::parse("[backlash]\ncycles = 0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("[backlash]"), "{e}");
    }
}
