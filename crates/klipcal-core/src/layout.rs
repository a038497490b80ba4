//! PURE: `layout.json`, the contract between the pylon generator and every consumer (solver,
//! user interfaces): where each pylon stands and which pairs of faces a user measures.
//! Serde types only; no geometry logic here.

use serde::{Deserialize, Serialize};

/// The current schema version.
pub const LAYOUT_VERSION: u32 = 1;

/// A printed calibration layout.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Layout {
    /// Schema version, [`LAYOUT_VERSION`].
    pub version: u32,
    /// `"corexy"` or `"cartesian"`.
    pub kinematics: String,
    /// Every pylon.
    pub pylons: Vec<Pylon>,
    /// Every pair of outer faces a user measures.
    pub pairs: Vec<Pair>,
}

/// One printed slab.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pylon {
    /// e.g. `"A1"`.
    pub id: String,
    /// Centre in printer XY millimetres.
    pub center: [f64; 2],
    /// Direction of the measured faces' normal, degrees from +X.
    pub normal_deg: f64,
    /// Slab thickness along the normal, mm.
    pub thickness: f64,
    /// Slab length across the normal, mm.
    pub length: f64,
    /// Height, mm.
    pub height: f64,
}

/// One measured distance: from the outer face of `from` to the far face of `to`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pair {
    /// e.g. `"A-D1"`.
    pub id: String,
    /// Group id, e.g. `"A"`.
    pub group: String,
    /// Pylon id of the first face.
    pub from: String,
    /// Pylon id of the far face.
    pub to: String,
    /// Measuring direction, degrees from +X.
    pub direction_deg: f64,
    /// Commanded outer edge-to-edge distance, mm.
    pub nominal_mm: f64,
}
