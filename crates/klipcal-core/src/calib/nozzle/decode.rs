//! A camera snapshot's bytes (JPEG from crowsnest/ustreamer/camera-streamer, PNG from a user's
//! own files) as grey pixels: the one decoder the daemon, the offline command and the bench use.

use anyhow::Context;

/// A JPEG or PNG file's pixels as grey (luma), with its width and height.
///
/// # Errors
/// Bytes that are not a JPEG or PNG picture the decoder can read.
pub fn decode_gray(bytes: &[u8]) -> anyhow::Result<(usize, usize, Vec<u8>)> {
    let img = image::load_from_memory(bytes)
        .context("expected a JPEG or PNG picture that the decoder can read")?;
    let g = img.into_luma8();
    let (w, h) = (g.width() as usize, g.height() as usize);
    Ok((w, h, g.into_raw()))
}
