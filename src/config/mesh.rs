//! `[mesh]`: thermal bed-mesh compensation settings, their defaults and ranges.

use serde::Deserialize;

use super::Error;

/// `[mesh]`: thermal bed-mesh compensation (`KLIPCAL_MESH_CAPTURE`, `_FOLLOW`, `_CHECK`).
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MeshConfig {
    /// Bed temperature for the capture, °C.
    pub bed_temp_c: f64,
    /// The frame thermistor: `[temperature_sensor NAME]`.
    pub frame_sensor: String,
    /// Take a mesh each time the frame temperature moved this much, °C…
    pub step_c: f64,
    /// …or this long passed since the last mesh, s.
    pub interval_s: f64,
    /// The frame has settled when it moved less than this over `interval_s`, °C.
    pub settle_c: f64,
    /// Fewest meshes before the capture may end.
    pub min_meshes: usize,
    /// Most meshes in one capture.
    pub max_meshes: usize,
    /// Longest capture, s (heaters off at the end).
    pub max_s: f64,
    /// Longest wait for the bed soak before the first mesh, s.
    pub soak_max_s: f64,
    /// Profiles are spaced so the nearest one is within this of the model, µm.
    pub tolerance_um: f64,
    /// KLIPCAL_MESH_CHECK halts a print start when a probed point is further than this from
    /// the model, mm (seed 001's 0.5 mm reference rule).
    pub reference_limit_mm: f64,
    /// Follow the frame temperature from the daemon's start (`KLIPCAL_MESH_FOLLOW` toggles it).
    pub follow: bool,
    /// At most one profile load per this many seconds.
    pub follow_interval_s: f64,
    /// A load that would change the mesh by more than this is refused, µm.
    pub jump_limit_um: f64,
    /// When heating and cooling have their own profiles: the frame counts as cooling once it
    /// fell this far below its highest reading, and as heating again once it rose this far
    /// above its lowest, °C.
    pub trend_c: f64,
    /// Following goes on this far outside the captured frame range (the nearest end's
    /// profile stays loaded) before it stops, °C; 0: it stops at the range's ends.
    pub range_margin_c: f64,
}

impl Default for MeshConfig {
    fn default() -> Self {
        Self {
            bed_temp_c: 60.0,
            frame_sensor: "frame".into(),
            step_c: 0.5,
            interval_s: 600.0,
            settle_c: 0.2,
            min_meshes: 3,
            max_meshes: 40,
            max_s: 10_800.0,
            soak_max_s: 5400.0,
            tolerance_um: 5.0,
            reference_limit_mm: 0.5,
            follow: false,
            follow_interval_s: 30.0,
            jump_limit_um: 50.0,
            trend_c: 0.3,
            range_margin_c: 0.0,
        }
    }
}

impl MeshConfig {
    /// The follower's policy from these settings.
    #[must_use]
    pub(crate) fn follow_policy(&self) -> crate::calib::mesh_follow::FollowPolicy {
        crate::calib::mesh_follow::FollowPolicy {
            tolerance_um: self.tolerance_um,
            min_interval_s: self.follow_interval_s,
            jump_limit_um: self.jump_limit_um,
            trend_c: self.trend_c,
            range_margin_c: self.range_margin_c,
            ..Default::default()
        }
    }
    /// Checks the `[mesh]` values' ranges.
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(super) fn validate(&self) -> Result<(), Error> {
        let me = self;
        if !me
            .frame_sensor
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            || me.frame_sensor.is_empty()
        {
            return Err(Error::Invalid {
                key: "mesh.frame_sensor",
                value: format!("{:?}", me.frame_sensor),
                expected:
                    "the name of a [temperature_sensor NAME] section (letters, digits, '_', '-')",
            });
        }
        for (key, v, lo, hi, expected) in [
            (
                "mesh.bed_temp_c",
                me.bed_temp_c,
                0.0,
                130.0,
                "°C from 0 to 130",
            ),
            ("mesh.step_c", me.step_c, 0.05, 20.0, "°C from 0.05 to 20"),
            (
                "mesh.interval_s",
                me.interval_s,
                5.0,
                7200.0,
                "seconds from 5 to 7200",
            ),
            ("mesh.settle_c", me.settle_c, 0.0, 10.0, "°C from 0 to 10"),
            (
                "mesh.max_s",
                me.max_s,
                60.0,
                86_400.0,
                "seconds from 60 to 86400",
            ),
            (
                "mesh.soak_max_s",
                me.soak_max_s,
                0.0,
                14_400.0,
                "seconds from 0 to 14400",
            ),
            (
                "mesh.tolerance_um",
                me.tolerance_um,
                0.5,
                100.0,
                "µm from 0.5 to 100",
            ),
            (
                "mesh.reference_limit_mm",
                me.reference_limit_mm,
                0.01,
                5.0,
                "mm from 0.01 to 5",
            ),
            (
                "mesh.follow_interval_s",
                me.follow_interval_s,
                1.0,
                3600.0,
                "seconds from 1 to 3600",
            ),
            (
                "mesh.jump_limit_um",
                me.jump_limit_um,
                1.0,
                1000.0,
                "µm from 1 to 1000",
            ),
            ("mesh.trend_c", me.trend_c, 0.05, 5.0, "°C from 0.05 to 5"),
            (
                "mesh.range_margin_c",
                me.range_margin_c,
                0.0,
                5.0,
                "°C from 0 to 5",
            ),
        ] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Error::Invalid {
                    key,
                    value: v.to_string(),
                    expected,
                });
            }
        }
        if !(2..=200).contains(&me.min_meshes)
            || me.max_meshes < me.min_meshes
            || me.max_meshes > 200
        {
            return Err(Error::Invalid {
                key: "mesh.min_meshes",
                value: format!("{} (mesh.max_meshes = {})", me.min_meshes, me.max_meshes),
                expected: "2 ≤ min_meshes ≤ max_meshes ≤ 200 (a fit needs two meshes)",
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::Config;

    #[test]
    fn the_follow_range_margin_is_a_setting_off_by_default_and_refused_by_name_out_of_range() {
        // Issue 26 B.3: following stops at the captured range's ends unless told otherwise.
        assert_eq!(Config::default().mesh.range_margin_c, 0.0);
        assert_eq!(Config::default().mesh.follow_policy().range_margin_c, 0.0);
        let cfg = Config::parse("[mesh]\nrange_margin_c = 0.5\n").unwrap();
        assert_eq!(cfg.mesh.follow_policy().range_margin_c, 0.5);
        for bad in ["-0.1", "5.5", "nan"] {
            let err = Config::parse(&format!("[mesh]\nrange_margin_c = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("mesh.range_margin_c") && err.contains("°C from 0 to 5"),
                "{err}"
            );
        }
    }
}
