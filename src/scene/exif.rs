//! The few EXIF values that say how a photograph was exposed: exposure
//! time, f-number, ISO speed and whether white balance was automatic.
//! [`super::photographs`] compares them across a capture's images to
//! decide whether they need per-image appearance.
//!
//! EXIF lives in a JPEG's APP1 segment ("Exif\0\0", then a TIFF file: a
//! byte-order mark, the offset of IFD0, whose tag 0x8769 points to the Exif
//! IFD holding the exposure tags; EXIF 2.32, sections 4.5 and 4.6). Only
//! what is needed is read, from the file's first [`HEADER_BYTES`]; a file
//! without EXIF, or with EXIF this reader cannot follow, gives `None`:
//! the caller then measures the images instead.

use std::path::Path;

/// APP1 comes before the image data, and phones keep it under 64 KiB
/// (a JPEG segment's length is 16 bits).
const HEADER_BYTES: u64 = 1 << 17;

/// Tags (EXIF 2.32, table 7 and table 8).
const EXIF_IFD_POINTER: u16 = 0x8769;
const EXPOSURE_TIME: u16 = 0x829A;
const F_NUMBER: u16 = 0x829D;
const ISO_SPEED: u16 = 0x8827;
const WHITE_BALANCE: u16 = 0xA403;

/// How one photograph was exposed, as far as its EXIF says.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Exposure {
    /// Seconds.
    pub exposure_time: Option<f64>,
    pub f_number: Option<f64>,
    pub iso: Option<f64>,
    /// `Some(true)` for automatic white balance (tag value 0), `Some(false)`
    /// for manual (1).
    pub auto_white_balance: Option<bool>,
}

impl Exposure {
    /// The light a pixel gathers relative to another exposure, in stops:
    /// log2(time × ISO / f-number²) (the f-number taken as 1 where not
    /// given, since a phone's aperture is fixed). `None` without time and
    /// ISO.
    pub fn stops(&self) -> Option<f64> {
        let time = self.exposure_time?;
        let iso = self.iso?;
        let f = self.f_number.unwrap_or(1.0);
        let gathered = time * iso / (f * f);
        (gathered > 0.0 && gathered.is_finite()).then(|| gathered.log2())
    }
}

/// The exposure recorded in the JPEG at `path`, or `None` where it has no
/// EXIF this reader can follow (a PNG, a frame extracted from a video, a
/// file that cannot be read).
pub fn read_exposure(path: &Path) -> Option<Exposure> {
    let bytes = crate::files::read_regular_prefix(path, HEADER_BYTES).ok()?;
    exposure_in_jpeg(&bytes)
}

/// [`read_exposure`] on a JPEG's first bytes.
pub fn exposure_in_jpeg(bytes: &[u8]) -> Option<Exposure> {
    let tiff = app1_exif(bytes)?;
    parse_tiff(tiff)
}

/// The TIFF file inside the first APP1 segment that starts "Exif\0\0".
fn app1_exif(bytes: &[u8]) -> Option<&[u8]> {
    if bytes.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    let mut at = 2;
    loop {
        let marker = bytes.get(at..at + 2)?;
        if marker[0] != 0xFF {
            return None;
        }
        // Start of scan: the headers are over.
        if marker[1] == 0xDA {
            return None;
        }
        let length = u16::from_be_bytes([*bytes.get(at + 2)?, *bytes.get(at + 3)?]) as usize;
        if length < 2 {
            return None;
        }
        let body = bytes.get(at + 4..at + 2 + length)?;
        if marker[1] == 0xE1 && body.starts_with(b"Exif\0\0") {
            return Some(&body[6..]);
        }
        at += 2 + length;
    }
}

/// A TIFF file's byte order.
#[derive(Clone, Copy)]
struct Tiff<'a> {
    bytes: &'a [u8],
    little_endian: bool,
}

impl Tiff<'_> {
    fn u16_at(&self, at: usize) -> Option<u16> {
        let b: [u8; 2] = self.bytes.get(at..at + 2)?.try_into().ok()?;
        Some(if self.little_endian {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    }

    fn u32_at(&self, at: usize) -> Option<u32> {
        let b: [u8; 4] = self.bytes.get(at..at + 4)?.try_into().ok()?;
        Some(if self.little_endian {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    /// The entries of the IFD at `offset`: (tag, type, count, the 4 bytes'
    /// position holding the value or its offset).
    fn entries(&self, offset: usize) -> Option<Vec<(u16, u16, u32, usize)>> {
        let count = self.u16_at(offset)? as usize;
        (0..count)
            .map(|i| {
                let at = offset + 2 + 12 * i;
                Some((
                    self.u16_at(at)?,
                    self.u16_at(at + 2)?,
                    self.u32_at(at + 4)?,
                    at + 8,
                ))
            })
            .collect()
    }

    /// A SHORT (type 3), LONG (4) or RATIONAL (5) value as a number.
    fn number(&self, kind: u16, count: u32, value_at: usize) -> Option<f64> {
        if count == 0 {
            return None;
        }
        match kind {
            3 => self.u16_at(value_at).map(f64::from),
            4 => self.u32_at(value_at).map(f64::from),
            5 => {
                let at = self.u32_at(value_at)? as usize;
                let (numerator, denominator) = (self.u32_at(at)?, self.u32_at(at + 4)?);
                (denominator != 0).then(|| numerator as f64 / denominator as f64)
            }
            _ => None,
        }
    }
}

fn parse_tiff(bytes: &[u8]) -> Option<Exposure> {
    let little_endian = match bytes.get(..2)? {
        b"II" => true,
        b"MM" => false,
        _ => return None,
    };
    let tiff = Tiff {
        bytes,
        little_endian,
    };
    if tiff.u16_at(2)? != 42 {
        return None;
    }
    let ifd0 = tiff.u32_at(4)? as usize;
    let mut exposure = Exposure::default();
    let mut exif_ifd = None;
    let mut read = |entries: Vec<(u16, u16, u32, usize)>, exif_ifd: &mut Option<usize>| {
        for (tag, kind, count, value_at) in entries {
            let value = tiff.number(kind, count, value_at);
            match tag {
                EXIF_IFD_POINTER => *exif_ifd = value.map(|v| v as usize),
                EXPOSURE_TIME => exposure.exposure_time = value,
                F_NUMBER => exposure.f_number = value,
                ISO_SPEED => exposure.iso = value,
                WHITE_BALANCE => exposure.auto_white_balance = value.map(|v| v == 0.0),
                _ => {}
            }
        }
    };
    read(tiff.entries(ifd0)?, &mut exif_ifd);
    if let Some(offset) = exif_ifd {
        read(tiff.entries(offset)?, &mut None);
    }
    Some(exposure)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A JPEG header with an APP1 EXIF segment (big-endian TIFF when
    /// `motorola`) holding an exposure time of `time_den`⁻¹ s, f/`f10`/10,
    /// ISO `iso` and white balance `white_balance` (0 auto, 1 manual), then
    /// the start of scan.
    pub(crate) fn jpeg_with_exif(
        motorola: bool,
        time_den: u32,
        f10: u32,
        iso: u16,
        white_balance: u16,
    ) -> Vec<u8> {
        let u16b = |v: u16| {
            if motorola {
                v.to_be_bytes().to_vec()
            } else {
                v.to_le_bytes().to_vec()
            }
        };
        let u32b = |v: u32| {
            if motorola {
                v.to_be_bytes().to_vec()
            } else {
                v.to_le_bytes().to_vec()
            }
        };
        let entry = |tag: u16, kind: u16, count: u32, value: Vec<u8>| {
            let mut e = u16b(tag);
            e.extend(u16b(kind));
            e.extend(u32b(count));
            let mut v = value;
            v.resize(4, 0);
            e.extend(v);
            e
        };
        // Layout: header (8), IFD0 at 8 with one entry (2 + 12 + 4 = 18),
        // Exif IFD at 26 with four entries (2 + 48 + 4 = 54), rationals at 80.
        let mut tiff = if motorola {
            b"MM".to_vec()
        } else {
            b"II".to_vec()
        };
        tiff.extend(u16b(42));
        tiff.extend(u32b(8));
        tiff.extend(u16b(1));
        tiff.extend(entry(EXIF_IFD_POINTER, 4, 1, u32b(26)));
        tiff.extend(u32b(0));
        assert_eq!(tiff.len(), 26);
        tiff.extend(u16b(4));
        tiff.extend(entry(EXPOSURE_TIME, 5, 1, u32b(80)));
        tiff.extend(entry(F_NUMBER, 5, 1, u32b(88)));
        tiff.extend(entry(ISO_SPEED, 3, 1, u16b(iso)));
        tiff.extend(entry(WHITE_BALANCE, 3, 1, u16b(white_balance)));
        tiff.extend(u32b(0));
        assert_eq!(tiff.len(), 80);
        tiff.extend(u32b(1));
        tiff.extend(u32b(time_den));
        tiff.extend(u32b(f10));
        tiff.extend(u32b(10));
        let mut body = b"Exif\0\0".to_vec();
        body.extend(tiff);
        let mut jpeg = vec![0xFF, 0xD8];
        // An APP0 segment first, as JFIF files have.
        jpeg.extend([0xFF, 0xE0, 0x00, 0x04, 0x00, 0x00]);
        jpeg.extend([0xFF, 0xE1]);
        jpeg.extend(((body.len() + 2) as u16).to_be_bytes());
        jpeg.extend(body);
        jpeg.extend([0xFF, 0xDA, 0x00, 0x02]);
        jpeg
    }

    #[test]
    fn reads_the_exposure_in_either_byte_order() {
        for motorola in [false, true] {
            let exposure = exposure_in_jpeg(&jpeg_with_exif(motorola, 60, 18, 200, 0)).unwrap();
            assert_eq!(exposure.exposure_time, Some(1.0 / 60.0));
            assert_eq!(exposure.f_number, Some(1.8));
            assert_eq!(exposure.iso, Some(200.0));
            assert_eq!(exposure.auto_white_balance, Some(true));
            let manual = exposure_in_jpeg(&jpeg_with_exif(motorola, 60, 18, 200, 1)).unwrap();
            assert_eq!(manual.auto_white_balance, Some(false));
        }
    }

    #[test]
    fn twice_the_time_or_the_iso_is_one_stop() {
        let base = exposure_in_jpeg(&jpeg_with_exif(false, 60, 18, 100, 0)).unwrap();
        let longer = exposure_in_jpeg(&jpeg_with_exif(false, 30, 18, 100, 0)).unwrap();
        let faster = exposure_in_jpeg(&jpeg_with_exif(false, 60, 18, 400, 0)).unwrap();
        let (b, l, f) = (
            base.stops().unwrap(),
            longer.stops().unwrap(),
            faster.stops().unwrap(),
        );
        assert!((l - b - 1.0).abs() < 1e-12, "{l} vs {b}");
        assert!((f - b - 2.0).abs() < 1e-12, "{f} vs {b}");
    }

    #[test]
    fn files_without_exif_or_cut_short_give_none() {
        assert_eq!(exposure_in_jpeg(b"\x89PNG\r\n\x1a\n"), None);
        assert_eq!(
            exposure_in_jpeg(&[0xFF, 0xD8, 0xFF, 0xDA, 0, 2]),
            None,
            "no APP1 before the scan"
        );
        let whole = jpeg_with_exif(true, 60, 18, 100, 0);
        for cut in [3, 10, 20, 40, 80, 100, whole.len() - 10] {
            // Whatever is read from a cut file must not panic; a cut inside
            // the EXIF IFD loses it.
            let _ = exposure_in_jpeg(&whole[..cut]);
        }
        assert_eq!(exposure_in_jpeg(&whole[..40]), None);
    }
}
