//! The install manifest (`printer_data/klipcal/install.json`): each file install changed with
//! its original bytes and what install added, so uninstall can restore or clean it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::files::read_opt;

/// One file install changed.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub(super) struct Entry {
    /// Its bytes before the first install (`None`: install created it).
    pub(super) original: Option<String>,
    /// What install wrote last.
    pub(super) installed: String,
    /// Whole lines install added (taken out again if the user changed the file since).
    #[serde(default)]
    pub(super) added_lines: Vec<String>,
    /// A section install added (`[update_manager klipcal]`).
    #[serde(default)]
    pub(super) section: Option<String>,
}

/// What install did, for uninstall.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub(super) struct Manifest {
    pub(super) version: String,
    /// Text files by absolute path.
    pub(super) files: BTreeMap<PathBuf, Entry>,
    /// Files install created outright (binary, release_info.json): removed on uninstall.
    pub(super) created: Vec<PathBuf>,
    /// The systemd unit, when install wrote one.
    pub(super) unit: Option<PathBuf>,
    /// The uid of the iframe webcam install registered with Moonraker (klipcal's page).
    #[serde(default)]
    pub(super) webcam: Option<String>,
}

/// A planned text change.
pub(super) struct Change {
    pub(super) path: PathBuf,
    pub(super) before: Option<String>,
    pub(super) after: String,
    pub(super) added_lines: Vec<String>,
    pub(super) section: Option<String>,
}

pub(super) fn manifest_path(pd: &Path) -> PathBuf {
    pd.join("klipcal/install.json")
}

pub(super) fn load_manifest(pd: &Path) -> anyhow::Result<Option<Manifest>> {
    match read_opt(&manifest_path(pd))? {
        Some(t) => Ok(Some(serde_json::from_str(&t).with_context(|| {
            format!("reading {}", manifest_path(pd).display())
        })?)),
        None => Ok(None),
    }
}
