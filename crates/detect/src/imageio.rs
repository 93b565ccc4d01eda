//! Reading uploaded images safely: the header first (format, dimensions), checked
//! against the camera and a pixel budget *before* any decoding, then a full decode with
//! allocation limits to prove the file is complete. A decompression bomb (a small file
//! declaring a huge image) is refused from its header alone.

use crate::gray::Gray;
use image::{ImageFormat, ImageReader, Limits};
use std::io::Cursor;

#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct ImageMeta {
    pub format: &'static str,
    pub width: u32,
    pub height: u32,
}

#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    #[error("a PNG or JPEG image, got {0}")]
    UnsupportedFormat(String),
    #[error("at most {max} pixels, the header declares {width}×{height}")]
    TooLarge { width: u32, height: u32, max: u64 },
    #[error(
        "an image of {expected_w}×{expected_h} pixels (the camera's size), got {width}×{height}"
    )]
    SizeMismatch {
        width: u32,
        height: u32,
        expected_w: u32,
        expected_h: u32,
    },
    #[error("a complete, decodable image: {0}")]
    Undecodable(String),
}

/// A reader with its format fixed from the magic bytes, and the format's name.
type Reader<'a> = (ImageReader<Cursor<&'a [u8]>>, &'static str);

fn reader(bytes: &[u8]) -> Result<Reader<'_>, ImageError> {
    let fmt = match image::guess_format(bytes) {
        Ok(ImageFormat::Png) => ("png", ImageFormat::Png),
        Ok(ImageFormat::Jpeg) => ("jpeg", ImageFormat::Jpeg),
        Ok(other) => return Err(ImageError::UnsupportedFormat(format!("{other:?}"))),
        Err(_) => {
            return Err(ImageError::UnsupportedFormat(
                "bytes that are not a known image format".into(),
            ))
        }
    };
    let mut r = ImageReader::new(Cursor::new(bytes));
    r.set_format(fmt.1);
    Ok((r, fmt.0))
}

/// Format and dimensions from the header only.
pub fn header(bytes: &[u8]) -> Result<ImageMeta, ImageError> {
    let (r, format) = reader(bytes)?;
    let (width, height) = r.into_dimensions().map_err(undecodable)?;
    Ok(ImageMeta {
        format,
        width,
        height,
    })
}

/// Check an uploaded image: header within `max_pixels`, dimensions equal to
/// `expected` when given, then a full, allocation-limited decode.
pub fn inspect(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<ImageMeta, ImageError> {
    decode(bytes, expected, max_pixels).map(|(meta, _)| meta)
}

/// [`inspect`], keeping the decoded pixels as the detector reads them: grey levels
/// 0..255 (16-bit precision kept).
///
/// A JPEG's own luma (the Y of its YCbCr) is decoded directly, without upsampling the
/// chroma and converting to RGB and back to grey: a third less time on a 1080p colour
/// frame, and the level the camera encoded rather than one recomputed from rounded
/// RGB. Grey JPEGs read as the general decoder reads them, one copy fewer; PNGs and
/// JPEGs stored as RGB or CMYK (no luma to take) go through the general decoder.
pub fn decode_gray(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<(ImageMeta, Gray), ImageError> {
    decode(bytes, expected, max_pixels).map(|(meta, img)| (meta, Gray::from_dynamic(&img)))
}

/// The checks and the decode of [`decode_gray`], its pixels as decoded (a JPEG's luma as
/// 8-bit grey): [`inspect`] needs no more.
fn decode(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<(ImageMeta, image::DynamicImage), ImageError> {
    let meta = checked_header(bytes, expected, max_pixels)?;
    if meta.format == "jpeg" {
        if let Some(luma) = jpeg_luma(bytes, &meta)? {
            return Ok((meta, image::DynamicImage::ImageLuma8(luma)));
        }
    }
    let (mut r, _) = reader(bytes)?;
    let mut limits = Limits::default();
    limits.max_image_width = Some(meta.width);
    limits.max_image_height = Some(meta.height);
    // 16-bit RGBA at most, plus decoder scratch.
    limits.max_alloc = Some(meta.width as u64 * meta.height as u64 * 8 + (64 << 20));
    r.limits(limits);
    let img = r.decode().map_err(undecodable)?;
    Ok((meta, img))
}

/// The header, checked against the pixel budget and the expected size before anything
/// is decoded; and for a JPEG, that the file is whole.
fn checked_header(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    max_pixels: u64,
) -> Result<ImageMeta, ImageError> {
    let meta = header(bytes)?;
    let pixels = meta.width as u64 * meta.height as u64;
    if pixels > max_pixels || meta.width == 0 || meta.height == 0 {
        return Err(ImageError::TooLarge {
            width: meta.width,
            height: meta.height,
            max: max_pixels,
        });
    }
    if let Some((w, h)) = expected {
        if (meta.width, meta.height) != (w, h) {
            return Err(ImageError::SizeMismatch {
                width: meta.width,
                height: meta.height,
                expected_w: w,
                expected_h: h,
            });
        }
    }
    // The JPEG decoder fills a file cut short with grey and says nothing; the PNG one
    // catches it by the checksums. A JPEG is whole when its end-of-image marker follows
    // the image's entropy-coded data.
    if meta.format == "jpeg" && !jpeg_is_whole(bytes) {
        return Err(ImageError::Undecodable(
            "a JPEG cut short: no end-of-image marker after its image data".into(),
        ));
    }
    Ok(meta)
}

/// The luma plane of a YCbCr or grey JPEG (the decoder `image` itself uses, with its
/// options, asked for grey output); `None` for a JPEG stored in another colour space.
fn jpeg_luma(bytes: &[u8], meta: &ImageMeta) -> Result<Option<image::GrayImage>, ImageError> {
    use zune_core::colorspace::ColorSpace;
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(false)
        .set_max_width(meta.width as usize)
        .set_max_height(meta.height as usize)
        .jpeg_set_out_colorspace(ColorSpace::Luma);
    let mut d = zune_jpeg::JpegDecoder::new_with_options(
        zune_core::bytestream::ZCursor::new(bytes),
        options,
    );
    d.decode_headers().map_err(undecodable)?;
    if !matches!(
        d.input_colorspace(),
        Some(ColorSpace::YCbCr | ColorSpace::Luma)
    ) {
        return Ok(None);
    }
    let px = d.decode().map_err(undecodable)?;
    let (w, h, n) = (meta.width, meta.height, px.len());
    let mismatch = || ImageError::Undecodable(format!("{n} luma samples for a {w}×{h} JPEG"));
    // Exactly one sample a pixel (`from_raw` alone would also take a longer buffer).
    if n as u64 != u64::from(w) * u64::from(h) {
        return Err(mismatch());
    }
    image::GrayImage::from_raw(w, h, px)
        .map(Some)
        .ok_or_else(mismatch)
}

fn undecodable(e: impl std::fmt::Display) -> ImageError {
    ImageError::Undecodable(e.to_string())
}

/// Does the JPEG carry an end-of-image marker (`FF D9`) after its first scan? The
/// segments before the scan are stepped over by their lengths (an EXIF thumbnail inside
/// APP1 has an end marker of its own); inside entropy-coded data `FF` is always followed
/// by `00` or a restart marker, so the first `FF D9` there is the image's end.
fn jpeg_is_whole(bytes: &[u8]) -> bool {
    let mut i = 2;
    while i + 1 < bytes.len() {
        if bytes[i] != 0xFF {
            return false;
        }
        let marker = bytes[i + 1];
        match marker {
            0xFF => i += 1,
            0xDA => return bytes[i..].windows(2).any(|w| w == [0xFF, 0xD9]),
            0x01 | 0xD0..=0xD7 => i += 2,
            _ => {
                let Some(len) = bytes.get(i + 2..i + 4) else {
                    return false;
                };
                i += 2 + u16::from_be_bytes([len[0], len[1]]) as usize;
            }
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    pub fn png(w: u32, h: u32) -> Vec<u8> {
        let img =
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([((x * 7 + y * 3) % 255) as u8]));
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png)
            .unwrap();
        out
    }

    #[test]
    fn accepts_png_of_the_camera_size() {
        let m = inspect(&png(64, 48), Some((64, 48)), 1 << 20).unwrap();
        assert_eq!((m.format, m.width, m.height), ("png", 64, 48));
    }

    #[test]
    fn refuses_wrong_size_truncation_and_other_formats() {
        let p = png(64, 48);
        assert!(matches!(
            inspect(&p, Some((640, 480)), 1 << 20),
            Err(ImageError::SizeMismatch { .. })
        ));
        assert!(matches!(
            inspect(&p[..p.len() / 2], Some((64, 48)), 1 << 20),
            Err(ImageError::Undecodable(_))
        ));
        assert!(matches!(
            inspect(b"GIF89a......", None, 1 << 20),
            Err(ImageError::UnsupportedFormat(_))
        ));
        assert!(matches!(
            inspect(b"hello", None, 1 << 20),
            Err(ImageError::UnsupportedFormat(_))
        ));
    }

    fn jpeg(w: u32, h: u32) -> Vec<u8> {
        let img =
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([((x * 5 + y * 11) % 255) as u8]));
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 92)
            .encode_image(&img)
            .unwrap();
        out
    }

    /// A JPEG cut at any point after its header is refused (the decoder alone pads it
    /// with grey); the whole file, and one with bytes after its end, are accepted.
    #[test]
    fn refuses_a_truncated_jpeg() {
        let j = jpeg(64, 48);
        assert!(inspect(&j, Some((64, 48)), 1 << 20).is_ok());
        for cut in [j.len() / 2, j.len() - 2, j.len() - 1, j.len() * 3 / 4] {
            assert!(
                matches!(
                    inspect(&j[..cut], Some((64, 48)), 1 << 20),
                    Err(ImageError::Undecodable(_))
                ),
                "cut at {cut} of {}",
                j.len()
            );
        }
        let mut trailer = j.clone();
        trailer.extend_from_slice(b"trailing metadata");
        assert!(inspect(&trailer, Some((64, 48)), 1 << 20).is_ok());
    }

    /// An RGB JPEG of smooth, moderately saturated colour (no channel clips).
    fn colour_jpeg(w: u32, h: u32) -> Vec<u8> {
        let img = image::RgbImage::from_fn(w, h, |x, y| {
            let v = (40 + (x * 3 + y * 2) % 170) as u8;
            image::Rgb([v, v.saturating_add(30), v / 2 + 20])
        });
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
            .encode_image(&img)
            .unwrap();
        out
    }

    /// A colour JPEG reads as its own luma: the Rec. 601 grey of the RGB the general
    /// decoder makes of it (which that luma is, up to the RGB's rounding), not the
    /// general decoder's Rec. 709 grey; a grey JPEG reads exactly as the general
    /// decoder reads it.
    #[test]
    fn jpegs_read_as_their_luma() {
        let c = colour_jpeg(97, 61);
        let (meta, gray) = decode_gray(&c, Some((97, 61)), 1 << 20).unwrap();
        assert_eq!((meta.format, gray.width, gray.height), ("jpeg", 97, 61));
        let rgb = image::load_from_memory(&c).unwrap().to_rgb8();
        let worst = rgb
            .pixels()
            .zip(&gray.data)
            .map(|(p, &y)| {
                let [r, g, b] = p.0.map(f32::from);
                (0.299 * r + 0.587 * g + 0.114 * b - y).abs()
            })
            .fold(0.0, f32::max);
        assert!(worst <= 1.5, "luma off the decoded RGB's by {worst} levels");
        let g = jpeg(64, 48);
        let (_, gray) = decode_gray(&g, None, 1 << 20).unwrap();
        let general = Gray::from_dynamic(&image::load_from_memory(&g).unwrap());
        assert_eq!(gray.data, general.data);
        // Cut short, the colour one is refused as the grey one is.
        assert!(matches!(
            decode_gray(&c[..c.len() * 2 / 3], None, 1 << 20),
            Err(ImageError::Undecodable(_))
        ));
    }

    /// A CMYK JPEG (written by Pillow) has no luma plane: it reads as the general
    /// decoder's grey of its RGB.
    #[test]
    fn cmyk_jpegs_read_through_the_general_decoder() {
        let c = include_bytes!("../testdata/cmyk_32x24.jpg");
        let (meta, gray) = decode_gray(c, Some((32, 24)), 1 << 20).unwrap();
        assert_eq!((meta.format, gray.width, gray.height), ("jpeg", 32, 24));
        let general = Gray::from_dynamic(&image::load_from_memory(c).unwrap());
        assert_eq!(gray.data, general.data);
        let spread = gray.data.iter().fold(0.0f32, |m, v| m.max(*v))
            - gray.data.iter().fold(255.0f32, |m, v| m.min(*v));
        assert!(spread > 50.0, "a pattern, not a flat grey: {spread}");
    }

    /// CRC-32 (PNG chunks), bitwise.
    fn crc32(data: &[u8]) -> u32 {
        let mut c = 0xffff_ffffu32;
        for b in data {
            c ^= *b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xedb8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    #[test]
    fn refuses_a_bomb_from_its_header() {
        // A valid PNG header declaring 100000×100000, then nothing.
        let mut p = png(1, 1);
        p[16..20].copy_from_slice(&100_000u32.to_be_bytes());
        p[20..24].copy_from_slice(&100_000u32.to_be_bytes());
        let crc = crc32(&p[12..29]);
        p[29..33].copy_from_slice(&crc.to_be_bytes());
        assert!(matches!(
            inspect(&p, None, 50_000_000),
            Err(ImageError::TooLarge { .. })
        ));
    }
}
