//! What a driver gate keeps of a fixed-seed run (the cpu engine's,
//! `ngp_driver_gate.rs`, and the gpu engine's, `ngp_gpu_driver_gate.rs`):
//! every step's loss bits and the CRC-32C of every checkpoint tensor, of a
//! rendered view's pixels, of the viewer's texture (gpu only) and of the
//! checkpoint file's bytes apart from its format version; written to and
//! read from a fixture as text, one fact a line.
//!
//! A run's f32 sums depend on what computed it (the cpu's kernels, the
//! gpu's adapter and driver), so a record names its origin: on the same
//! origin a run must match the record bit for bit, on another its losses
//! within a relative tolerance the gate justifies.

use zrak::model::RenderedPixel;
use zrak::model::checkpoint::Checkpoint;

/// A gate's fixture: where it lives, what its origin line is called
/// (`kernels`, `device`), the comment it starts with and how many steps a
/// run records.
pub struct Fixture {
    pub path: &'static str,
    pub origin_key: &'static str,
    pub header: &'static str,
    pub steps: usize,
}

/// What one fixed-seed run produced, as a fixture holds it.
#[derive(Debug, Clone, PartialEq)]
pub struct GateRecord {
    /// What computed the run (the cpu's kernels, the gpu's device).
    pub origin: String,
    /// The bits of every step's loss.
    pub losses: Vec<u32>,
    /// Every checkpoint tensor: name, length, CRC-32C of its bits.
    pub tensors: Vec<(String, usize, u32)>,
    /// CRC-32C of a validation view's pixels (colour, opacity, depth bits).
    pub pixels: u32,
    /// CRC-32C of the colour image drawn into the viewer's texture.
    pub texture: Option<u32>,
    /// CRC-32C of the checkpoint file's bytes, the version zeroed.
    pub checkpoint: u32,
}

/// The format version's bytes in a checkpoint file: after the 8-byte
/// magic, a little-endian u32 (src/model/checkpoint.rs).
const VERSION_BYTES: std::ops::Range<usize> = 8..12;

/// CRC-32C of `u32`s, little-endian.
pub fn crc_of_words(words: &[u32]) -> u32 {
    let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
    zrak::crc32c::crc32c(&bytes)
}

/// The bits of every pixel's colour, opacity and depth.
pub fn pixel_bits(pixels: &[RenderedPixel]) -> Vec<u32> {
    pixels
        .iter()
        .flat_map(|p| [p.rgb[0], p.rgb[1], p.rgb[2], p.opacity, p.depth])
        .map(f32::to_bits)
        .collect()
}

/// A checkpoint's bytes as a file holds them.
pub fn file_bytes(checkpoint: &Checkpoint) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.zrak");
    checkpoint.save(&path).unwrap();
    std::fs::read(path).unwrap()
}

impl GateRecord {
    /// The record of a run from `origin` that took steps of `losses` and
    /// ended in `checkpoint`, rendered `pixels` and drew `texture`.
    pub fn new(
        origin: String,
        losses: Vec<u32>,
        checkpoint: &Checkpoint,
        pixels: &[RenderedPixel],
        texture: Option<&[u8]>,
    ) -> Self {
        let mut bytes = file_bytes(checkpoint);
        bytes[VERSION_BYTES].fill(0);
        Self {
            origin,
            losses,
            tensors: checkpoint
                .tensors
                .iter()
                .map(|(name, values)| {
                    let bits: Vec<u32> = values.iter().map(|v| v.to_bits()).collect();
                    (name.clone(), values.len(), crc_of_words(&bits))
                })
                .collect(),
            pixels: crc_of_words(&pixel_bits(pixels)),
            texture: texture.map(zrak::crc32c::crc32c),
            checkpoint: zrak::crc32c::crc32c(&bytes),
        }
    }

    pub fn to_text(&self, fixture: &Fixture) -> String {
        let mut text = fixture.header.to_string();
        text += &format!("{} {}\n", fixture.origin_key, self.origin);
        for (step, loss) in self.losses.iter().enumerate() {
            text += &format!("loss {step} {loss:08x}\n");
        }
        for (name, len, crc) in &self.tensors {
            text += &format!("tensor {name} {len} {crc:08x}\n");
        }
        text += &format!("pixels {:08x}\n", self.pixels);
        if let Some(texture) = self.texture {
            text += &format!("texture {texture:08x}\n");
        }
        text += &format!("checkpoint {:08x}\n", self.checkpoint);
        text
    }

    pub fn parse(text: &str, fixture: &Fixture) -> Result<Self, String> {
        let hex = |s: &str| u32::from_str_radix(s, 16).map_err(|e| format!("`{s}`: {e}"));
        let mut record = GateRecord {
            origin: String::new(),
            losses: Vec::new(),
            tensors: Vec::new(),
            pixels: 0,
            texture: None,
            checkpoint: 0,
        };
        for (number, line) in text.lines().enumerate() {
            let at = |problem: String| format!("{} line {}: {problem}", fixture.path, number + 1);
            // The origin may hold spaces ("llvmpipe (LLVM 15.0.6, …)").
            if let Some(origin) = line
                .strip_prefix(fixture.origin_key)
                .and_then(|rest| rest.strip_prefix(' '))
            {
                record.origin = origin.to_string();
                continue;
            }
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.as_slice() {
                [] => {}
                [first, ..] if first.starts_with('#') => {}
                ["loss", step, bits] => {
                    if step.parse::<usize>() != Ok(record.losses.len()) {
                        return Err(at(format!("step {step} out of order")));
                    }
                    record.losses.push(hex(bits).map_err(at)?);
                }
                ["tensor", name, len, crc] => record.tensors.push((
                    name.to_string(),
                    len.parse()
                        .map_err(|e| at(format!("length `{len}`: {e}")))?,
                    hex(crc).map_err(at)?,
                )),
                ["pixels", crc] => record.pixels = hex(crc).map_err(at)?,
                ["texture", crc] => record.texture = Some(hex(crc).map_err(at)?),
                ["checkpoint", crc] => record.checkpoint = hex(crc).map_err(at)?,
                _ => return Err(at(format!("unexpected line `{line}`"))),
            }
        }
        if record.origin.is_empty() || record.losses.len() != fixture.steps {
            return Err(format!(
                "{}: needs a `{}` line and {} losses",
                fixture.path, fixture.origin_key, fixture.steps
            ));
        }
        Ok(record)
    }

    /// The fixture's record.
    pub fn read(fixture: &Fixture) -> Self {
        let text = std::fs::read_to_string(fixture.path)
            .unwrap_or_else(|e| panic!("reading {}: {e}", fixture.path));
        Self::parse(&text, fixture).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Asserts that this run reproduces `expected`: bit for bit from the
    /// same origin; from another, every loss within `loss_tolerance`
    /// (relative) and the same tensors by name and length.
    pub fn assert_reproduces(&self, expected: &Self, fixture: &Fixture, loss_tolerance: f64) {
        if self.origin == expected.origin {
            for (step, (got, want)) in self.losses.iter().zip(&expected.losses).enumerate() {
                assert_eq!(
                    got,
                    want,
                    "step {step}'s loss: {} here, {} recorded",
                    f32::from_bits(*got),
                    f32::from_bits(*want)
                );
            }
            assert_eq!(self.tensors, expected.tensors, "checkpoint tensors");
            assert_eq!(self.pixels, expected.pixels, "rendered pixels");
            assert_eq!(self.texture, expected.texture, "texture bytes");
            assert_eq!(
                self.checkpoint, expected.checkpoint,
                "checkpoint file bytes"
            );
            assert_eq!(self, expected);
        } else {
            eprintln!(
                "{} {} here, {} in the record: losses compared within {loss_tolerance}",
                fixture.origin_key, self.origin, expected.origin
            );
            for (step, (got, want)) in self.losses.iter().zip(&expected.losses).enumerate() {
                let (got, want) = (f32::from_bits(*got) as f64, f32::from_bits(*want) as f64);
                assert!(
                    (got - want).abs() <= loss_tolerance * want.abs(),
                    "step {step}'s loss: {got} here, {want} recorded"
                );
            }
            let names = |r: &Self| -> Vec<(String, usize)> {
                r.tensors.iter().map(|(n, l, _)| (n.clone(), *l)).collect()
            };
            assert_eq!(names(self), names(expected), "checkpoint tensors");
        }
    }
}
