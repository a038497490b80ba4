//! Daemon settings: a TOML file whose every key has an embedded default, so `klipcal serve`
//! runs with no file on a standard printer host. Unknown keys and bad values are errors that
//! name the key, the value and what is expected. Reads no environment beyond `HOME`.

use std::path::{Path, PathBuf};

use serde::Deserialize;

/// A settings error a user can cause.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read.
    #[error("cannot read config file {path}: {cause}")]
    Read {
        /// The path tried.
        path: PathBuf,
        /// The I/O error. Shown in the message, and deliberately not the error's `source()`:
        /// a `{:#}` chain would print it twice.
        cause: std::io::Error,
    },
    /// The file is not valid TOML or has an unknown key or a value of the wrong type.
    #[error("config file {path}: {message}")]
    Parse {
        /// The path read.
        path: PathBuf,
        /// toml's message, which names the line, the key and what was expected.
        message: String,
    },
    /// A `[soak]` key has a value out of range.
    #[error("config key {0}")]
    Soak(#[from] crate::calib::soak::SoakParamsError),
    /// A `[backlash]` key has a value out of range.
    #[error("config [backlash]: {0}")]
    Backlash(String),
    /// A key has a value out of range.
    #[error("config key `{key}` = {value}: expected {expected}")]
    Invalid {
        /// Dotted key name, e.g. `moonraker.url`.
        key: &'static str,
        /// The value found.
        value: String,
        /// What would be accepted.
        expected: &'static str,
    },
}

/// All settings. See `config/klipcal.toml` for every key and its default.
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// How to reach Moonraker.
    pub moonraker: MoonrakerConfig,
    /// Logging.
    pub log: LogConfig,
    /// The daemon's own files.
    pub daemon: DaemonConfig,
    /// Differential A/B (X/Y) calibration sessions.
    pub ab: AbConfig,
    /// Thermal soak detection (bed power watching, paper §3.1).
    pub soak: crate::calib::soak::SoakParams,
    /// Backlash measurement (seed 004): verdict thresholds, smooth_time budget, jog sizes.
    pub backlash: BacklashConfig,
    /// The daemon's own HTTP API and page.
    pub http: HttpConfig,
    /// Thermal bed-mesh compensation (seed 002): capture, fit, profiles, follow, check.
    pub mesh: MeshConfig,
    /// Keys of earlier versions found in the file and ignored (for a warning at start).
    #[serde(skip)]
    pub retired_keys: Vec<String>,
}

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
}

/// `[http]`: the daemon's page and API (`src/http/`).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    /// Serve the page and API at all.
    pub enabled: bool,
    /// Address and port to listen on; `0.0.0.0:7150` listens on the LAN.
    pub bind: String,
    /// Addresses (CIDR ranges) allowed without an API key; the default is what a standard
    /// Moonraker install trusts: loopback, the private ranges, link-local.
    pub trusted_clients: Vec<String>,
    /// When set, a request carrying `X-Api-Key: <this>` is allowed from any address.
    pub api_key: String,
    /// Host names (besides IP addresses, `localhost`, single-label names and `*.local`) a
    /// changing request may be addressed to: a guard against DNS rebinding.
    pub host_names: Vec<String>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            bind: "0.0.0.0:7150".into(),
            trusted_clients: [
                "127.0.0.0/8",
                "10.0.0.0/8",
                "172.16.0.0/12",
                "192.168.0.0/16",
                "169.254.0.0/16",
                "::1/128",
                "fe80::/10",
            ]
            .iter()
            .map(|s| (*s).to_string())
            .collect(),
            api_key: String::new(),
            host_names: Vec::new(),
        }
    }
}

impl HttpConfig {
    /// The trusted ranges, parsed.
    ///
    /// # Errors
    /// An entry that is not an address or a CIDR range.
    pub(crate) fn trusted(&self) -> Result<Vec<ipnet::IpNet>, Error> {
        self.trusted_clients
            .iter()
            .map(|t| {
                t.parse::<ipnet::IpNet>()
                    .or_else(|_| t.parse::<std::net::IpAddr>().map(ipnet::IpNet::from))
                    .map_err(|_| Error::Invalid {
                        key: "http.trusted_clients",
                        value: format!("{t:?}"),
                        expected: "addresses or CIDR ranges such as \"192.168.1.0/24\" or \"::1\"",
                    })
            })
            .collect()
    }
}

/// `[backlash]`: the guided camera measurement and its statistics (seed 004).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct BacklashConfig {
    /// Cycles per axis (KLIPCAL_BACKLASH_START CYCLES= overrides).
    pub cycles: usize,
    /// Approach distance, mm (the seed's 1 mm).
    pub approach_mm: f64,
    /// Coarse jog, mm.
    pub coarse_mm: f64,
    /// Fine jog of odd cycles, mm (the reading resolution).
    pub fine_mm: f64,
    /// Fine jog of even cycles, mm (0: off); removes a stopping bias proportional to the jog.
    pub small_fine_mm: f64,
    /// Furthest a jog may take the nozzle from the camera point, mm.
    pub max_travel_mm: f64,
    /// "Centred" is refused while more than this short of the camera point, mm.
    pub plausible_mm: f64,
    /// At or below this no compensation is needed (seed: 0.01–0.02 mm).
    pub none_needed_max_mm: f64,
    /// From this compensation is needed (seed: ~0.05 mm).
    pub needed_from_mm: f64,
    /// The verdict's cut between the two.
    pub compensate_from_mm: f64,
    /// Per-cycle sd assumed with fewer than 3 cycles, mm.
    pub prior_cycle_sd_mm: f64,
    /// The compensation's extra acceleration 2·b/t² may use this fraction of max_accel.
    pub accel_budget_fraction: f64,
    /// Outlier cut, robust sd from the median.
    pub outlier_sigmas: f64,
    /// The nozzle camera's name in Moonraker's webcam list (KLIPCAL_BACKLASH_CAMERA); empty:
    /// the only webcam there is.
    pub webcam: String,
    /// After a move, wait this long before the first frame (vibration, camera latency), s.
    pub camera_settle_s: f64,
}

impl Default for BacklashConfig {
    fn default() -> Self {
        let p = crate::calib::backlash::BacklashParams::default();
        let g = crate::calib::backlash_guide::GuideParams::default();
        BacklashConfig {
            cycles: g.cycles,
            approach_mm: g.approach_mm,
            coarse_mm: g.coarse_mm,
            fine_mm: g.fine_mm,
            small_fine_mm: g.small_fine_mm,
            max_travel_mm: g.max_travel_mm,
            plausible_mm: g.plausible_mm,
            none_needed_max_mm: p.none_needed_max_mm,
            needed_from_mm: p.needed_from_mm,
            compensate_from_mm: p.compensate_from_mm,
            prior_cycle_sd_mm: p.prior_cycle_sd_mm,
            accel_budget_fraction: p.accel_budget_fraction,
            outlier_sigmas: p.outlier_sigmas,
            webcam: String::new(),
            camera_settle_s: 0.3,
        }
    }
}

impl BacklashConfig {
    /// The statistics' settings.
    pub(crate) fn params(&self) -> crate::calib::backlash::BacklashParams {
        crate::calib::backlash::BacklashParams {
            none_needed_max_mm: self.none_needed_max_mm,
            needed_from_mm: self.needed_from_mm,
            compensate_from_mm: self.compensate_from_mm,
            jog_resolution_mm: self.fine_mm,
            prior_cycle_sd_mm: self.prior_cycle_sd_mm,
            accel_budget_fraction: self.accel_budget_fraction,
            outlier_sigmas: self.outlier_sigmas,
            scale_rel_sd: 0.0,
            repeat_sd_mm: 0.0,
            step_mm: 0.0,
        }
    }

    /// The guided procedure's settings.
    pub(crate) fn guide(&self) -> crate::calib::backlash_guide::GuideParams {
        crate::calib::backlash_guide::GuideParams {
            cycles: self.cycles,
            approach_mm: self.approach_mm,
            coarse_mm: self.coarse_mm,
            fine_mm: self.fine_mm,
            small_fine_mm: self.small_fine_mm,
            max_travel_mm: self.max_travel_mm,
            plausible_mm: self.plausible_mm,
            crossing: true,
        }
    }
}

/// `[ab]`: defaults of a differential rotation_distance calibration session (each session
/// stores its own copy, with the start call's arguments).
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AbConfig {
    /// `paper` (two groups along the motor directions) or `full` (four groups: also the
    /// in-plane shear from one print).
    pub layout: String,
    /// Bed temperature for the print and the readings; 0 prints on an unheated bed (no soak).
    pub bed_temp_c: f64,
    /// Nozzle temperature.
    pub nozzle_temp_c: f64,
    /// Readings per pair before the pair counts as measured.
    pub readings_per_pair: usize,
    /// Wait after the print for the part to cool on the hot bed before asking for readings.
    pub cooldown_s: f64,
    /// Longest the bed is held hot after the print; then heaters go off.
    pub hold_max_s: f64,
    /// A change of rotation_distance beyond this needs FORCE=1.
    pub max_change_pct: f64,
    /// Longest wait for the bed to reach equilibrium before printing anyway is refused.
    pub soak_max_s: f64,
    /// Readings further than this from a pair's nominal distance are refused, mm.
    pub reading_tolerance_mm: f64,
    /// The caliper's last digit, mm (0.01 for most digital calipers, 0.02 or 0.05 for a
    /// vernier): a reading is typed with at most its decimals, and its rounding enters the
    /// stated uncertainty.
    pub caliper_resolution_mm: f64,
    /// Where the in-plane shear goes: `motors` (A/B rotation distances absorb it, as the paper's
    /// iteration does; Cartesian printers still send it to Klipper's skew correction) or
    /// `klipper_skew` (Klipper's skew_correction takes it, saved as profile `klipcal`).
    pub shear_to: String,
    /// The start macro the slicer calls (e.g. `START_PRINT`); empty: klipcal looks for
    /// `PRINT_START` and `START_PRINT` ([`crate::klipper::find_start_macro`]).
    pub start_macro: String,
}

impl Default for AbConfig {
    fn default() -> Self {
        Self {
            layout: "paper".into(),
            bed_temp_c: 60.0,
            nozzle_temp_c: 215.0,
            readings_per_pair: 5,
            cooldown_s: 720.0,
            hold_max_s: 1800.0,
            max_change_pct: 3.0,
            soak_max_s: 5400.0,
            reading_tolerance_mm: 2.0,
            caliper_resolution_mm: 0.01,
            shear_to: "motors".into(),
            start_macro: String::new(),
        }
    }
}

/// `[moonraker]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MoonrakerConfig {
    /// Websocket URL, `ws://host:port/websocket`.
    pub url: String,
    /// API key, sent when Moonraker requires authorization; empty for none.
    pub api_key: String,
    /// How long one request may wait for its reply.
    pub request_timeout_s: f64,
    /// First reconnect delay.
    pub reconnect_min_s: f64,
    /// Cap of the exponential reconnect backoff.
    pub reconnect_max_s: f64,
}

/// `[log]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct LogConfig {
    /// `error`, `warn`, `info`, `debug` or `trace`; `RUST_LOG` overrides.
    pub level: String,
}

/// `[daemon]`
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DaemonConfig {
    /// Where the daemon keeps its database; `~` expands to the home folder.
    pub data_dir: String,
}

impl Default for MoonrakerConfig {
    fn default() -> Self {
        Self {
            url: "ws://127.0.0.1:7125/websocket".into(),
            api_key: String::new(),
            request_timeout_s: 30.0,
            reconnect_min_s: 0.5,
            reconnect_max_s: 30.0,
        }
    }
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            level: "info".into(),
        }
    }
}

impl Default for DaemonConfig {
    fn default() -> Self {
        Self {
            data_dir: "~/printer_data/klipcal".into(),
        }
    }
}

/// The conventional path, `~/printer_data/config/klipcal.toml`.
pub(crate) fn default_path() -> PathBuf {
    expand_home("~/printer_data/config/klipcal.toml")
}

/// Expands a leading `~/` to `$HOME/`.
pub fn expand_home(path: &str) -> PathBuf {
    match (path.strip_prefix("~/"), std::env::var_os("HOME")) {
        (Some(rest), Some(home)) => Path::new(&home).join(rest),
        _ => PathBuf::from(path),
    }
}

impl Config {
    /// Loads settings: `explicit` must exist; without it the default path is read when present,
    /// else the embedded defaults are used.
    ///
    /// # Errors
    /// An unreadable file, bad TOML, an unknown key or a value out of range.
    pub(crate) fn load(explicit: Option<&Path>) -> Result<Self, Error> {
        let path = match explicit {
            Some(p) => p.to_path_buf(),
            None => {
                let p = default_path();
                if !p.exists() {
                    return Ok(Self::default());
                }
                p
            }
        };
        let text = std::fs::read_to_string(&path).map_err(|cause| Error::Read {
            path: path.clone(),
            cause,
        })?;
        Self::parse(&text).map_err(|e| match e {
            Error::Parse { message, .. } => Error::Parse { path, message },
            other => other,
        })
    }

    /// Parses and validates TOML text.
    ///
    /// # Errors
    /// Bad TOML, an unknown key or a value out of range.
    pub fn parse(text: &str) -> Result<Self, Error> {
        let parse_error = |e: toml::de::Error| Error::Parse {
            path: PathBuf::new(),
            message: e.to_string(),
        };
        let mut table: toml::Table = toml::from_str(text).map_err(parse_error)?;
        // `[soak]` keys of earlier versions are read and ignored (named in a warning), so an
        // old settings file still loads.
        let mut retired = Vec::new();
        if let Some(toml::Value::Table(soak)) = table.get_mut("soak") {
            for key in crate::calib::soak::RETIRED_KEYS {
                if soak.remove(*key).is_some() {
                    retired.push(format!("soak.{key}"));
                }
            }
        }
        let mut cfg: Config = table.try_into().map_err(parse_error)?;
        cfg.retired_keys = retired;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value's range (also after a command-line override).
    ///
    /// # Errors
    /// The first key whose value is out of range.
    pub(crate) fn validate(&self) -> Result<(), Error> {
        let m = &self.moonraker;
        if m.url.starts_with("wss://") {
            return Err(Error::Invalid {
                key: "moonraker.url",
                value: format!("{:?}", m.url),
                expected: "a plain ws:// URL: klipcal runs on the printer host and talks to \
                           Moonraker over loopback (\"ws://127.0.0.1:7125/websocket\"); TLS \
                           is not built in",
            });
        }
        if !m.url.starts_with("ws://") {
            return Err(Error::Invalid {
                key: "moonraker.url",
                value: format!("{:?}", m.url),
                expected: "a websocket URL such as \"ws://127.0.0.1:7125/websocket\"",
            });
        }
        let positive = [
            ("moonraker.request_timeout_s", m.request_timeout_s),
            ("moonraker.reconnect_min_s", m.reconnect_min_s),
            ("moonraker.reconnect_max_s", m.reconnect_max_s),
        ];
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                return Err(Error::Invalid {
                    key,
                    value: v.to_string(),
                    expected: "a number of seconds above 0 and at most 86400",
                });
            }
        }
        if m.reconnect_max_s < m.reconnect_min_s {
            return Err(Error::Invalid {
                key: "moonraker.reconnect_max_s",
                value: m.reconnect_max_s.to_string(),
                expected: "a value not below moonraker.reconnect_min_s",
            });
        }
        let ab = &self.ab;
        if !ab
            .start_macro
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_')
        {
            return Err(Error::Invalid {
                key: "ab.start_macro",
                value: format!("{:?}", ab.start_macro),
                expected: "a Klipper macro name (letters, digits and '_'), or \"\" to find \
                           PRINT_START or START_PRINT",
            });
        }
        if !["paper", "full"].contains(&ab.layout.as_str()) {
            return Err(Error::Invalid {
                key: "ab.layout",
                value: format!("{:?}", ab.layout),
                expected: "\"paper\" or \"full\"",
            });
        }
        let ranges = [
            (
                "ab.bed_temp_c",
                ab.bed_temp_c,
                0.0,
                130.0,
                "°C from 0 (unheated) to 130",
            ),
            (
                "ab.nozzle_temp_c",
                ab.nozzle_temp_c,
                150.0,
                320.0,
                "°C from 150 to 320",
            ),
            (
                "ab.cooldown_s",
                ab.cooldown_s,
                0.0,
                7200.0,
                "seconds from 0 to 7200",
            ),
            (
                "ab.hold_max_s",
                ab.hold_max_s,
                0.0,
                14_400.0,
                "seconds from 0 to 14400",
            ),
            (
                "ab.max_change_pct",
                ab.max_change_pct,
                0.01,
                20.0,
                "a percentage from 0.01 to 20",
            ),
            (
                "ab.soak_max_s",
                ab.soak_max_s,
                0.0,
                14_400.0,
                "seconds from 0 to 14400",
            ),
            (
                "ab.reading_tolerance_mm",
                ab.reading_tolerance_mm,
                0.01,
                50.0,
                "mm from 0.01 to 50",
            ),
            (
                "ab.caliper_resolution_mm",
                ab.caliper_resolution_mm,
                0.001,
                0.1,
                "the caliper's last digit in mm, from 0.001 to 0.1 (0.01 for most digital \
                 calipers)",
            ),
        ];
        for (key, v, lo, hi, expected) in ranges {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(Error::Invalid {
                    key,
                    value: v.to_string(),
                    expected,
                });
            }
        }
        if ab.cooldown_s >= ab.hold_max_s {
            return Err(Error::Invalid {
                key: "ab.cooldown_s",
                value: format!("{} (ab.hold_max_s = {})", ab.cooldown_s, ab.hold_max_s),
                expected: "a cool-down shorter than ab.hold_max_s: the hold limit turns the \
                           heaters off before the readings are asked for otherwise",
            });
        }
        if !(3..=20).contains(&ab.readings_per_pair) {
            return Err(Error::Invalid {
                key: "ab.readings_per_pair",
                value: ab.readings_per_pair.to_string(),
                expected: "a whole number from 3 to 20",
            });
        }
        if self.http.bind.parse::<std::net::SocketAddr>().is_err() {
            return Err(Error::Invalid {
                key: "http.bind",
                value: format!("{:?}", self.http.bind),
                expected: "an address and port such as \"0.0.0.0:7150\" or \"127.0.0.1:7150\"",
            });
        }
        self.http.trusted()?;
        if let Some(h) = self.http.host_names.iter().find(|h| {
            h.is_empty()
                || !h
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '.' || c == '-')
        }) {
            return Err(Error::Invalid {
                key: "http.host_names",
                value: format!("{h:?}"),
                expected: "host names such as \"printer.example.org\"",
            });
        }
        let me = &self.mesh;
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
        self.soak.validate()?;
        self.backlash
            .params()
            .validate()
            .and_then(|()| self.backlash.guide().validate())
            .map_err(|e| Error::Backlash(e.to_string()))?;
        if !["error", "warn", "info", "debug", "trace"].contains(&self.log.level.as_str()) {
            return Err(Error::Invalid {
                key: "log.level",
                value: format!("{:?}", self.log.level),
                expected: "one of \"error\", \"warn\", \"info\", \"debug\", \"trace\"",
            });
        }
        Ok(())
    }

    /// The HTTP base URL derived from the websocket URL (`ws://h:p/websocket` → `http://h:p`).
    pub(crate) fn http_base(&self) -> String {
        let url = &self.moonraker.url;
        let (scheme, rest) = ("http://", url.strip_prefix("ws://").unwrap_or(url));
        let host = rest.split('/').next().unwrap_or(rest);
        format!("{scheme}{host}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cooldown_not_shorter_than_the_hold_limit_is_refused_at_load() {
        let e = Config::parse("[ab]\ncooldown_s = 1800\nhold_max_s = 1800\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ab.cooldown_s") && e.contains("hold_max_s"),
            "{e}"
        );
        assert!(Config::parse("[ab]\ncooldown_s = 600\nhold_max_s = 1800\n").is_ok());
    }

    #[test]
    fn a_caliper_resolution_out_of_range_is_refused_by_name() {
        for bad in ["0", "0.5", "-0.01"] {
            let e = Config::parse(&format!("[ab]\ncaliper_resolution_mm = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("ab.caliper_resolution_mm") && e.contains("last digit"),
                "{e}"
            );
        }
        let c = Config::parse("[ab]\ncaliper_resolution_mm = 0.02\n").unwrap();
        assert_eq!(c.ab.caliper_resolution_mm, 0.02);
        assert_eq!(Config::default().ab.caliper_resolution_mm, 0.01);
    }

    #[test]
    fn empty_file_gives_the_embedded_defaults() {
        let cfg = Config::parse("").unwrap();
        assert_eq!(cfg, Config::default());
        assert_eq!(cfg.moonraker.url, "ws://127.0.0.1:7125/websocket");
        assert_eq!(cfg.http_base(), "http://127.0.0.1:7125");
    }

    #[test]
    fn the_documented_example_parses_and_equals_the_defaults() {
        let text = include_str!("../config/klipcal.toml");
        assert_eq!(Config::parse(text).unwrap(), Config::default());
    }

    #[test]
    fn an_unknown_key_is_named_in_the_error() {
        let err = Config::parse("[moonraker]\nurll = \"ws://x/websocket\"\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("urll"), "{msg}");
        assert!(msg.contains("url"), "{msg}");
    }

    #[test]
    fn a_bad_value_names_key_value_and_expectation() {
        let err = Config::parse("[moonraker]\nrequest_timeout_s = -1.0\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("moonraker.request_timeout_s"), "{msg}");
        assert!(msg.contains("-1"), "{msg}");
        assert!(msg.contains("expected"), "{msg}");
        let err = Config::parse("[log]\nlevel = \"loud\"\n").unwrap_err();
        assert!(err.to_string().contains("\"loud\""));
        let err = Config::parse("[moonraker]\nurl = \"http://x\"\n").unwrap_err();
        assert!(err.to_string().contains("moonraker.url"));
    }

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

    #[test]
    fn a_value_of_the_wrong_type_is_an_error_naming_the_key() {
        let err = Config::parse("[moonraker]\nrequest_timeout_s = \"ten\"\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("request_timeout_s"), "{msg}");
    }

    #[test]
    fn a_settings_file_that_cannot_be_read_names_its_cause_once() {
        let err = Config::load(Some(Path::new("/nonexistent/klipcal.toml"))).unwrap_err();
        let shown = format!("{:#}", anyhow::Error::new(err));
        assert_eq!(shown.matches("No such file").count(), 1, "{shown}");
        assert!(shown.contains("/nonexistent/klipcal.toml"), "{shown}");
    }

    #[test]
    fn ab_start_macro_is_a_macro_name_or_empty() {
        let c = Config::parse("[ab]\nstart_macro = \"START_PRINT\"\n").unwrap();
        assert_eq!(c.ab.start_macro, "START_PRINT");
        assert_eq!(Config::default().ab.start_macro, "");
        let err = Config::parse("[ab]\nstart_macro = \"START PRINT; G28\"\n").unwrap_err();
        assert!(err.to_string().contains("ab.start_macro"), "{err}");
    }
}
