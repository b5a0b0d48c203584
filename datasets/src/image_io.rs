//! PNG and JPEG decoding straight into a caller-owned buffer (e.g. a shared-memory frame
//! slot), and a header-only size probe. The format is told by the file's first bytes. Never panics on bad files: every failure is a
//! [`DatasetError::Image`] (or `NotFound` / `Io`) naming the file.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use image::codecs::jpeg::JpegDecoder;
use image::codecs::png::PngDecoder;
use image::{ColorType, DynamicImage, ImageDecoder};

use crate::DatasetError;

fn image_err(path: &Path, detail: impl Into<String>) -> DatasetError {
    DatasetError::Image {
        path: path.to_path_buf(),
        detail: detail.into(),
    }
}

fn open(path: &Path) -> Result<File, DatasetError> {
    File::open(path).map_err(|source| {
        if source.kind() == std::io::ErrorKind::NotFound {
            DatasetError::NotFound {
                path: path.to_path_buf(),
                what: "image file".into(),
            }
        } else {
            DatasetError::Io {
                path: path.to_path_buf(),
                source,
            }
        }
    })
}

/// Width and height of a PNG (read from its 24-byte header only: signature + IHDR) or a
/// JPEG (its header segments).
pub fn image_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    let mut head = [0u8; 24];
    let mut file = open(path)?;
    let n = file
        .read(&mut head)
        .map_err(|e| image_err(path, format!("cannot read the header: {e}")))?;
    if head[..2] == [0xff, 0xd8] {
        let decoder = JpegDecoder::new(BufReader::new(open(path)?))
            .map_err(|e| image_err(path, format!("cannot read the JPEG header: {e}")))?;
        return Ok(decoder.dimensions());
    }
    if n < 24 {
        return Err(image_err(
            path,
            "cannot read the PNG header: file too short",
        ));
    }
    if head[..8] != *b"\x89PNG\r\n\x1a\n" || head[12..16] != *b"IHDR" {
        return Err(image_err(
            path,
            "neither a PNG (bad signature or no IHDR chunk) nor a JPEG file",
        ));
    }
    let w = u32::from_be_bytes([head[16], head[17], head[18], head[19]]);
    let h = u32::from_be_bytes([head[20], head[21], head[22], head[23]]);
    if w == 0 || h == 0 {
        return Err(image_err(path, format!("invalid PNG size {w}x{h}")));
    }
    Ok((w, h))
}

/// Whether the file at `path` starts as a JPEG (`FF D8`).
fn is_jpeg(path: &Path) -> Result<bool, DatasetError> {
    let mut head = [0u8; 2];
    let n = open(path)?
        .read(&mut head)
        .map_err(|e| image_err(path, format!("cannot read: {e}")))?;
    Ok(n == 2 && head == [0xff, 0xd8])
}

/// Decodes the PNG or JPEG at `path` as 8-bit gray into `dst` (row-major, `width * height`
/// bytes).
///
/// An 8-bit gray image of the expected size is decoded directly into `dst` (no allocation for
/// the pixels); other colour types (RGB, RGBA, 16-bit, gray+alpha) are decoded into a scratch
/// image and converted to luma into `dst`. A size other than `width x height`, a `dst` of the
/// wrong length, or corrupt data gives [`DatasetError::Image`] naming the file.
pub fn decode_gray_into(
    path: &Path,
    dst: &mut [u8],
    width: u32,
    height: u32,
) -> Result<(), DatasetError> {
    let expected = (width as usize).checked_mul(height as usize);
    if expected != Some(dst.len()) {
        return Err(image_err(
            path,
            format!(
                "destination buffer has {} bytes, {width}x{height} needs {expected:?}",
                dst.len()
            ),
        ));
    }
    if is_jpeg(path)? {
        let decoder = JpegDecoder::new(BufReader::new(open(path)?))
            .map_err(|e| image_err(path, format!("cannot decode JPEG: {e}")))?;
        return decode_with(decoder, path, "JPEG", dst, width, height);
    }
    let decoder = PngDecoder::new(BufReader::new(open(path)?))
        .map_err(|e| image_err(path, format!("cannot decode PNG: {e}")))?;
    decode_with(decoder, path, "PNG", dst, width, height)
}

/// [`decode_gray_into`] with an open decoder of format `format`.
fn decode_with<D: ImageDecoder>(
    decoder: D,
    path: &Path,
    format: &str,
    dst: &mut [u8],
    width: u32,
    height: u32,
) -> Result<(), DatasetError> {
    let (w, h) = decoder.dimensions();
    if (w, h) != (width, height) {
        return Err(image_err(
            path,
            format!("size {w}x{h}, expected {width}x{height}"),
        ));
    }
    if decoder.color_type() == ColorType::L8 {
        return decoder
            .read_image(dst)
            .map_err(|e| image_err(path, format!("corrupt {format} data: {e}")));
    }
    let color = decoder.color_type();
    let gray = DynamicImage::from_decoder(decoder)
        .map_err(|e| image_err(path, format!("corrupt {format} data ({color:?}): {e}")))?
        .into_luma8();
    if gray.as_raw().len() != dst.len() {
        return Err(image_err(path, "converted image has an unexpected size"));
    }
    dst.copy_from_slice(gray.as_raw());
    Ok(())
}

/// Decodes a PNG or JPEG as 8-bit gray into a new buffer: `(width, height, pixels)`.
pub fn decode_gray(path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    let (w, h) = image_size(path)?;
    let len = (w as usize)
        .checked_mul(h as usize)
        .filter(|&n| n <= 1 << 30)
        .ok_or_else(|| image_err(path, format!("image too large: {w}x{h}")))?;
    let mut buf = vec![0u8; len];
    decode_gray_into(path, &mut buf, w, h)?;
    Ok((w, h, buf))
}
