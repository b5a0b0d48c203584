//! Image messages to 8-bit gray: the pixel encodings and compressed formats shoal reads,
//! a cheap probe (stamp and size, no pixel decoding) for the index pass, and the decoder the
//! replay uses.

use std::io::Cursor;

use image::codecs::jpeg::JpegDecoder;
use image::codecs::png::PngDecoder;
use image::{DynamicImage, ImageDecoder, RgbImage};

use super::msgs::{self, Bytes, Time};

/// The image message types shoal reads (all CDR-encoded).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ImageKind {
    /// `sensor_msgs/msg/Image`.
    RosRaw,
    /// `foxglove_msgs/msg/RawImage`.
    FoxgloveRaw,
    /// `sensor_msgs/msg/CompressedImage`.
    RosCompressed,
    /// `foxglove_msgs/msg/CompressedImage`.
    FoxgloveCompressed,
    /// ROS 1 `sensor_msgs/Image` ([`crate::ros1_bag`]).
    Ros1Raw,
    /// ROS 1 `sensor_msgs/CompressedImage`.
    Ros1Compressed,
}

impl ImageKind {
    /// The kind of schema `name`, if it is an image.
    pub fn of_schema(name: &str) -> Option<Self> {
        match name {
            msgs::names::IMAGE => Some(Self::RosRaw),
            msgs::names::FOXGLOVE_RAW_IMAGE => Some(Self::FoxgloveRaw),
            msgs::names::COMPRESSED_IMAGE => Some(Self::RosCompressed),
            msgs::names::FOXGLOVE_COMPRESSED_IMAGE => Some(Self::FoxgloveCompressed),
            _ => None,
        }
    }
}

/// The raw pixel encodings read: one byte per pixel (gray) or three (RGB / BGR order).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum RawEncoding {
    Mono8,
    Rgb8,
    Bgr8,
}

/// The raw encodings shoal reads, for error messages.
pub const RAW_ENCODINGS: &str = "mono8 (8UC1), rgb8, bgr8 (8UC3)";

fn raw_encoding(name: &str) -> Result<RawEncoding, String> {
    match name {
        "mono8" | "8UC1" => Ok(RawEncoding::Mono8),
        "rgb8" => Ok(RawEncoding::Rgb8),
        "bgr8" | "8UC3" => Ok(RawEncoding::Bgr8),
        other => Err(format!(
            "unknown pixel encoding \"{other}\" (shoal reads {RAW_ENCODINGS})"
        )),
    }
}

/// A raw image message's fields that matter.
struct Raw<'a> {
    stamp: Time,
    width: u32,
    height: u32,
    encoding: std::borrow::Cow<'a, str>,
    step: u32,
    data: Bytes<'a>,
}

/// A compressed image message's fields that matter.
struct Compressed<'a> {
    stamp: Time,
    data: Bytes<'a>,
}

enum Decoded<'a> {
    Raw(Raw<'a>),
    Compressed(Compressed<'a>),
}

fn parse(kind: ImageKind, bytes: &[u8]) -> Result<Decoded<'_>, String> {
    Ok(match kind {
        ImageKind::RosRaw => {
            let m: msgs::Image = msgs::decode(bytes)?;
            if m.is_bigendian > 1 {
                return Err(format!("is_bigendian = {}", m.is_bigendian));
            }
            Decoded::Raw(Raw {
                stamp: m.header.stamp,
                width: m.width,
                height: m.height,
                encoding: m.encoding,
                step: m.step,
                data: m.data,
            })
        }
        ImageKind::FoxgloveRaw => {
            let m: msgs::FoxgloveRawImage = msgs::decode(bytes)?;
            Decoded::Raw(Raw {
                stamp: m.timestamp,
                width: m.width,
                height: m.height,
                encoding: m.encoding,
                step: m.step,
                data: m.data,
            })
        }
        ImageKind::RosCompressed => {
            let m: msgs::CompressedImage = msgs::decode(bytes)?;
            Decoded::Compressed(Compressed {
                stamp: m.header.stamp,
                data: m.data,
            })
        }
        ImageKind::FoxgloveCompressed => {
            let m: msgs::FoxgloveCompressedImage = msgs::decode(bytes)?;
            Decoded::Compressed(Compressed {
                stamp: m.timestamp,
                data: m.data,
            })
        }
        ImageKind::Ros1Raw => {
            let m = crate::ros1_bag::msgs::image(bytes)?;
            if m.is_bigendian > 1 {
                return Err(format!("is_bigendian = {}", m.is_bigendian));
            }
            Decoded::Raw(Raw {
                stamp: ros1_time(m.stamp)?,
                width: m.width,
                height: m.height,
                encoding: m.encoding.into(),
                step: m.step,
                data: Bytes(m.data),
            })
        }
        ImageKind::Ros1Compressed => {
            let (stamp, _, data) = crate::ros1_bag::msgs::compressed_image(bytes)?;
            Decoded::Compressed(Compressed {
                stamp: ros1_time(stamp)?,
                data: Bytes(data),
            })
        }
    })
}

/// A ROS 1 stamp as a ROS 2 time (seconds beyond `i32` are an error).
fn ros1_time(t: crate::ros1_bag::msgs::Time) -> Result<Time, String> {
    let sec = i32::try_from(t.sec).map_err(|_| format!("stamp of {} s beyond 2038", t.sec))?;
    Ok(Time {
        sec,
        nanosec: t.nsec,
    })
}

/// What the index pass keeps of an image message: its header stamp and size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageProbe {
    /// Header stamp, ns.
    pub stamp_ns: i64,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

/// Stamp and size of an image message, with every check that does not need the pixels
/// decompressed (encoding known, sizes consistent, compressed format recognised).
pub fn probe(kind: ImageKind, bytes: &[u8]) -> Result<ImageProbe, String> {
    let (stamp, width, height) = match parse(kind, bytes)? {
        Decoded::Raw(r) => {
            raw_layout(&r)?;
            (r.stamp, r.width, r.height)
        }
        Decoded::Compressed(c) => {
            let (w, h) = compressed_size(c.data.0)?;
            (c.stamp, w, h)
        }
    };
    let stamp_ns = stamp
        .to_ns()
        .ok_or_else(|| format!("header stamp nanosec {} is not below 1e9", stamp.nanosec))?;
    if width == 0 || height == 0 {
        return Err(format!("empty image {width}x{height}"));
    }
    Ok(ImageProbe {
        stamp_ns,
        width,
        height,
    })
}

/// Checks a raw image's encoding and sizes; returns the encoding and bytes per pixel.
fn raw_layout(r: &Raw) -> Result<(RawEncoding, usize), String> {
    let enc = raw_encoding(&r.encoding)?;
    let bpp = if enc == RawEncoding::Mono8 { 1 } else { 3 };
    let row = r.width as usize * bpp;
    if (r.step as usize) < row {
        return Err(format!(
            "step {} shorter than a row of {} {} pixels",
            r.step, r.width, r.encoding
        ));
    }
    let need = (r.step as usize) * (r.height as usize);
    if r.data.0.len() < need {
        return Err(format!(
            "{} bytes of pixels, {}x{} at step {} needs {need}",
            r.data.0.len(),
            r.width,
            r.height,
            r.step
        ));
    }
    Ok((enc, bpp))
}

/// Width and height of a PNG or JPEG from its header.
fn compressed_size(data: &[u8]) -> Result<(u32, u32), String> {
    if data.starts_with(&[0xff, 0xd8]) {
        let d = JpegDecoder::new(Cursor::new(data)).map_err(|e| format!("bad JPEG: {e}"))?;
        Ok(d.dimensions())
    } else if data.starts_with(b"\x89PNG\r\n\x1a\n") {
        let d = PngDecoder::new(Cursor::new(data)).map_err(|e| format!("bad PNG: {e}"))?;
        Ok(d.dimensions())
    } else {
        Err(format!(
            "compressed data is neither JPEG nor PNG (starts {:02x?}); shoal reads jpeg and png",
            &data[..data.len().min(4)]
        ))
    }
}

/// Decodes the image message `bytes` of `kind` as 8-bit gray into `dst` (`width * height`
/// bytes). RGB and BGR become luma as the `image` crate computes it (the same as a colour
/// PNG read from a folder).
pub fn decode_gray_into(
    kind: ImageKind,
    bytes: &[u8],
    dst: &mut [u8],
    width: u32,
    height: u32,
) -> Result<(), String> {
    let img = match parse(kind, bytes)? {
        Decoded::Raw(r) => {
            if (r.width, r.height) != (width, height) {
                return Err(format!(
                    "size {}x{}, expected {width}x{height}",
                    r.width, r.height
                ));
            }
            return raw_to_gray(&r, dst);
        }
        Decoded::Compressed(c) => image::load_from_memory(c.data.0)
            .map_err(|e| format!("corrupt compressed image: {e}"))?,
    };
    if (img.width(), img.height()) != (width, height) {
        return Err(format!(
            "size {}x{}, expected {width}x{height}",
            img.width(),
            img.height()
        ));
    }
    let gray = img.into_luma8();
    if gray.as_raw().len() != dst.len() {
        return Err("destination buffer of the wrong size".into());
    }
    dst.copy_from_slice(gray.as_raw());
    Ok(())
}

/// [`decode_gray_into`] of the message `bytes` read from `path` (or why it could not be
/// read); an error names the file and `place`, the message's place in it.
pub(crate) fn decode_message_into(
    path: &std::path::Path,
    place: &str,
    kind: ImageKind,
    bytes: Result<&[u8], String>,
    dst: &mut [u8],
    (width, height): (u32, u32),
) -> Result<(), crate::DatasetError> {
    bytes
        .and_then(|b| decode_gray_into(kind, b, dst, width, height))
        .map_err(|detail| crate::DatasetError::Image {
            path: path.to_path_buf(),
            detail: format!("{place}: {detail}"),
        })
}

/// A raw image's rows (without step padding) as gray into `dst`.
fn raw_to_gray(r: &Raw, dst: &mut [u8]) -> Result<(), String> {
    let (enc, bpp) = raw_layout(r)?;
    let (w, h, step) = (r.width as usize, r.height as usize, r.step as usize);
    if dst.len() != w * h {
        return Err("destination buffer of the wrong size".into());
    }
    let rows = r.data.0.chunks(step).take(h);
    if enc == RawEncoding::Mono8 {
        for (src, out) in rows.zip(dst.chunks_exact_mut(w)) {
            out.copy_from_slice(&src[..w]);
        }
        return Ok(());
    }
    let mut rgb = Vec::with_capacity(w * h * 3);
    for src in rows {
        let row = &src[..w * bpp];
        if enc == RawEncoding::Rgb8 {
            rgb.extend_from_slice(row);
        } else {
            rgb.extend(row.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]));
        }
    }
    let img = RgbImage::from_raw(r.width, r.height, rgb).ok_or("RGB buffer of the wrong size")?;
    dst.copy_from_slice(DynamicImage::ImageRgb8(img).into_luma8().as_raw());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mcap_bag::msgs::{encode, Header, Image};

    fn image(encoding: &str, w: u32, h: u32, step: u32, data: &[u8]) -> Vec<u8> {
        encode(
            &Image {
                header: Header {
                    stamp: Time { sec: 1, nanosec: 5 },
                    frame_id: "cam".into(),
                },
                height: h,
                width: w,
                encoding: encoding.into(),
                is_bigendian: 0,
                step,
                data: Bytes(data),
            },
            64,
        )
        .unwrap()
    }

    #[test]
    fn mono_with_row_padding() {
        let bytes = image("mono8", 2, 2, 3, &[1, 2, 99, 3, 4, 99]);
        let p = probe(ImageKind::RosRaw, &bytes).unwrap();
        assert_eq!((p.stamp_ns, p.width, p.height), (1_000_000_005, 2, 2));
        let mut dst = [0u8; 4];
        decode_gray_into(ImageKind::RosRaw, &bytes, &mut dst, 2, 2).unwrap();
        assert_eq!(dst, [1, 2, 3, 4]);
    }

    #[test]
    fn bgr_is_rgb_swapped() {
        let rgb = [200u8, 10, 30, 0, 255, 0];
        let bgr = [30u8, 10, 200, 0, 255, 0];
        let (mut a, mut b) = ([0u8; 2], [0u8; 2]);
        decode_gray_into(
            ImageKind::RosRaw,
            &image("rgb8", 2, 1, 6, &rgb),
            &mut a,
            2,
            1,
        )
        .unwrap();
        decode_gray_into(
            ImageKind::RosRaw,
            &image("bgr8", 2, 1, 6, &bgr),
            &mut b,
            2,
            1,
        )
        .unwrap();
        assert_eq!(a, b);
        // Rec. 709 luma of pure green is 0.7152 * 255.
        assert_eq!(a[1], 182);
    }

    #[test]
    fn bad_encodings_and_sizes() {
        let e = probe(ImageKind::RosRaw, &image("bayer_rggb8", 2, 1, 2, &[0, 0])).unwrap_err();
        assert!(e.contains("unknown pixel encoding \"bayer_rggb8\""), "{e}");
        let e = probe(ImageKind::RosRaw, &image("mono8", 4, 2, 4, &[0; 7])).unwrap_err();
        assert!(e.contains("7 bytes of pixels"), "{e}");
        let e = probe(ImageKind::RosRaw, &image("rgb8", 4, 1, 4, &[0; 12])).unwrap_err();
        assert!(e.contains("step 4 shorter"), "{e}");
    }
}
