//! `klipcal-bench backlash`: the guided procedure of [`crate::calib::backlash_guide`] on
//! simulated axes and simulated people, beside the seed's single pass; then the camera
//! procedure (detection on rendered pictures, pixels → mm from known moves, the seed's cycles
//! from the image) and the click flow. The simulated axes and people are in `models`, the
//! guided bench in `guided`, the camera and click bench in `camera`.

mod camera;
mod guided;
mod models;
mod optic;

pub(crate) use guided::bench;
