//! The newest nozzle-camera frames a backlash measurement looked at, kept in memory (the last
//! few, never on disk) so klipcal's page can show them through klipcal's own API
//! (`GET /api/backlash/snapshot.jpg?seq=N`): the page is often opened inside Mainsail as an
//! iframe, or on a phone, where the webcam's own URL may not be reachable. Each frame carries
//! what the detector found in it, so the page marks the nozzle where the measurement saw it.
//! No I/O here: the camera code hands the bytes in.

use std::collections::VecDeque;
use std::sync::Mutex;

use serde::Serialize;

/// Frames kept: enough that the one a status named is still there when the page asks for it.
const KEEP: usize = 6;

/// What one kept frame shows, as the status gives it to the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SnapshotInfo {
    /// Its number (the page asks for the JPEG by it).
    pub seq: u64,
    /// The picture's size, px.
    pub width: usize,
    pub height: usize,
    /// Where in the measurement it was taken, in words.
    pub what: String,
    /// The nozzle's centre as the detector found it, px (pixel centres at integers).
    pub centre_px: Option<[f64; 2]>,
    /// Its outer radius, px.
    pub radius_px: Option<f64>,
    /// 1 sd of the centre, px.
    pub uncertainty_px: Option<f64>,
    /// Why detection refused the frame, when it did.
    pub refused: Option<String>,
    /// The click-in-snapshot flow waits for the person to click the nozzle's tip in it.
    pub click: bool,
    /// Where the page zooms in for the click, px (the last click, or the camera point once the
    /// scale is known) …
    pub hint_px: Option<[f64; 2]>,
    /// … and by how much.
    pub zoom: Option<f64>,
}

struct Frame {
    session: i64,
    jpeg: Vec<u8>,
    info: SnapshotInfo,
}

/// The kept frames.
#[derive(Default)]
pub(crate) struct Frames {
    inner: Mutex<(u64, VecDeque<Frame>)>,
}

impl Frames {
    /// Keeps `jpeg` of `session` (`info.seq` is assigned here) and returns its number.
    pub(crate) fn keep(&self, session: i64, jpeg: Vec<u8>, mut info: SnapshotInfo) -> u64 {
        let mut g = self
            .inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        g.0 += 1;
        info.seq = g.0;
        g.1.push_back(Frame {
            session,
            jpeg,
            info,
        });
        while g.1.len() > KEEP {
            g.1.pop_front();
        }
        g.0
    }

    /// The newest frame of `session`.
    pub(crate) fn newest(&self, session: i64) -> Option<SnapshotInfo> {
        let g = self
            .inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        g.1.iter()
            .rev()
            .find(|f| f.session == session)
            .map(|f| f.info.clone())
    }

    /// The frame numbered `seq`, or the newest.
    pub(crate) fn jpeg(&self, seq: Option<u64>) -> Option<Vec<u8>> {
        let g = self
            .inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        match seq {
            Some(n) => g.1.iter().find(|f| f.info.seq == n),
            None => g.1.back(),
        }
        .map(|f| f.jpeg.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(what: &str) -> SnapshotInfo {
        SnapshotInfo {
            seq: 0,
            width: 4,
            height: 3,
            what: what.into(),
            centre_px: Some([1.0, 2.0]),
            radius_px: None,
            uncertainty_px: None,
            refused: None,
            click: false,
            hint_px: None,
            zoom: None,
        }
    }

    #[test]
    fn frames_are_numbered_the_newest_per_session_is_shown_and_old_ones_go() {
        let f = Frames::default();
        assert!(f.jpeg(None).is_none() && f.newest(1).is_none());
        let a = f.keep(1, vec![1], info("a"));
        let b = f.keep(2, vec![2], info("b"));
        assert_eq!((a, b), (1, 2));
        assert_eq!(f.newest(1).unwrap().what, "a");
        assert_eq!(f.newest(2).unwrap().seq, 2);
        assert_eq!(f.jpeg(Some(1)), Some(vec![1]));
        assert_eq!(f.jpeg(None), Some(vec![2]));
        for k in 0..KEEP {
            f.keep(2, vec![9], info(&k.to_string()));
        }
        assert!(f.jpeg(Some(1)).is_none(), "the oldest frame is dropped");
        assert!(f.newest(1).is_none());
    }
}
