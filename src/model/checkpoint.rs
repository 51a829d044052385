//! Checkpoints: named f32 tensors plus a JSON header, written to a temporary
//! file and renamed into place, so a crash mid-write leaves the previous
//! checkpoint intact.
//!
//! Layout: the magic `ZRAKCKPT`, a little-endian u32 format version, a u64
//! header length, the header as JSON, the header's CRC-32C (u32), then
//! each tensor's stored bytes in the header's order. The header lists each
//! tensor's name, length, encoding (f32, or a dictionary of its distinct
//! values with bit-packed indices) and the CRC-32C of its stored bytes, so
//! a flipped bit anywhere is found on load and named. Version 1 files
//! (no checksum after the header, every tensor f32) are still read.

use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

const MAGIC: &[u8; 8] = b"ZRAKCKPT";
/// 2: a CRC-32C of the header and of each tensor, and tensors of few
/// distinct values stored as a dictionary. Files of version 1 (no
/// checksums) are still read.
const FORMAT_VERSION: u32 = 2;

/// A checkpoint in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    /// Model name, step, configuration, scene identity and anything else
    /// small; free-form JSON owned by the trainer.
    pub header: serde_json::Value,
    pub tensors: Vec<(String, Vec<f32>)>,
}

/// A checkpoint could not be read or written, by the kind a caller decides
/// on; each names the file and what is wrong.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The file cannot be read or written: not there, a folder or a pipe,
    /// a full disk, too little memory for its tensors.
    #[error("{path}: {problem}")]
    Io { path: PathBuf, problem: String },
    /// Not a checkpoint this zrak reads: other magic bytes, a format
    /// version from elsewhere, a header that is not zrak's.
    #[error("{path}: not a zrak checkpoint ({problem})")]
    Format { path: PathBuf, problem: String },
    /// A zrak checkpoint cut off before its end (a copy or a write that did
    /// not finish).
    #[error("{path}: not a zrak checkpoint ({problem})")]
    Truncated { path: PathBuf, problem: String },
    /// A zrak checkpoint whose bytes changed after it was written: a
    /// checksum that fails, a table that contradicts itself.
    #[error("{path}: the checkpoint is damaged: {problem}")]
    Damaged { path: PathBuf, problem: String },
    /// A checkpoint whose table is not that of the model it is loaded for
    /// (another model, or the same model in another configuration): a
    /// tensor the model does not have, or one of another length. The
    /// `problem` is the whole message after the path.
    #[error("{path}: {problem}")]
    OtherModel { path: PathBuf, problem: String },
    /// A model holding a value that is not finite: it had diverged.
    #[error("{path}: {problem}")]
    NonFinite { path: PathBuf, problem: String },
}

/// The table of contents of a version 1 file (no checksums).
#[derive(Deserialize)]
struct StoredHeaderV1 {
    header: serde_json::Value,
    tensors: Vec<(String, usize)>,
}

/// The table of contents of a version 2 file.
#[derive(Serialize, Deserialize)]
struct StoredHeader {
    header: serde_json::Value,
    tensors: Vec<StoredTensor>,
}

/// Where one tensor is in the file and how to check and decode it.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct StoredTensor {
    name: String,
    /// Values in the tensor.
    values: usize,
    encoding: Encoding,
    /// Bytes its stored form takes.
    bytes: u64,
    /// CRC-32C of those bytes.
    crc32c: u32,
}

/// How a tensor's values are stored. Both are exact: every value reads
/// back bit for bit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
enum Encoding {
    /// Each value as a little-endian f32.
    F32,
    /// The `distinct` values a tensor takes (little-endian f32), then each
    /// value's index among them in `bits` bits, packed from the lowest bit
    /// of each byte: for tensors of few distinct values (Adam's per-entry
    /// bias corrections are a function of how often the entry was updated;
    /// an occupancy grid still untrained is one value), so 1 to 16 bits a
    /// value where f32 takes 32.
    Dictionary { distinct: u32, bits: u8 },
    /// A bit per value, set where the value is not +0.0 (lowest bit of
    /// each byte first), then those `nonzero` values as f32: for tensors
    /// mostly zero (Adam's moments of hash-table entries no sample has
    /// touched yet).
    Sparse { nonzero: u64 },
}

/// The most distinct values a dictionary holds.
const MAX_DICTIONARY: usize = 1 << 16;

/// Bits that index `distinct` values: at least 1, so that the values a
/// file can declare are bounded by its size (8 per byte), and a damaged
/// count cannot ask for more memory than a small multiple of the file.
fn index_bits(distinct: usize) -> u8 {
    ((usize::BITS - distinct.saturating_sub(1).leading_zeros()) as u8).max(1)
}

/// The tensor as a dictionary and an index per value, if it takes at most
/// [`MAX_DICTIONARY`] distinct values (bit patterns, so -0 and NaN
/// payloads are kept).
fn dictionary_of(values: &[f32]) -> Option<(Vec<f32>, Vec<u16>)> {
    // Open addressing over twice the largest dictionary: the probe stops
    // early for the common case, a tensor of many values.
    const SLOTS: usize = 2 * MAX_DICTIONARY;
    let mut keys = vec![u32::MAX; SLOTS];
    let mut slot_index = vec![0u16; SLOTS];
    let mut used_max_key = false;
    let mut max_key_index = 0u16;
    let mut distinct: Vec<f32> = Vec::new();
    let mut indices = Vec::with_capacity(values.len());
    for &value in values {
        let key = value.to_bits();
        // u32::MAX marks an empty slot; that bit pattern (a NaN) is kept
        // aside.
        if key == u32::MAX {
            if !used_max_key {
                if distinct.len() == MAX_DICTIONARY {
                    return None;
                }
                used_max_key = true;
                max_key_index = distinct.len() as u16;
                distinct.push(value);
            }
            indices.push(max_key_index);
            continue;
        }
        let mut slot = (key.wrapping_mul(0x9E37_79B1) >> 15) as usize % SLOTS;
        loop {
            if keys[slot] == key {
                indices.push(slot_index[slot]);
                break;
            }
            if keys[slot] == u32::MAX {
                if distinct.len() == MAX_DICTIONARY {
                    return None;
                }
                keys[slot] = key;
                slot_index[slot] = distinct.len() as u16;
                indices.push(distinct.len() as u16);
                distinct.push(value);
                break;
            }
            slot = (slot + 1) % SLOTS;
        }
    }
    Some((distinct, indices))
}

/// A tensor in the form it is written (the smallest of the encodings):
/// the encoding and its bytes.
fn encode(values: &[f32]) -> (Encoding, Vec<u8>) {
    let nonzero = values.iter().filter(|v| v.to_bits() != 0).count();
    let sparse_bytes = values.len().div_ceil(8) + 4 * nonzero;
    let dictionary = encode_dictionary(values);
    let smallest_so_far = dictionary
        .as_ref()
        .map_or(4 * values.len(), |(_, bytes)| bytes.len());
    if sparse_bytes < smallest_so_far {
        let mut bytes = vec![0u8; values.len().div_ceil(8)];
        bytes.reserve(4 * nonzero);
        for (i, value) in values.iter().enumerate() {
            if value.to_bits() != 0 {
                bytes[i / 8] |= 1 << (i % 8);
            }
        }
        for value in values.iter().filter(|v| v.to_bits() != 0) {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        return (
            Encoding::Sparse {
                nonzero: nonzero as u64,
            },
            bytes,
        );
    }
    dictionary.unwrap_or_else(|| (Encoding::F32, bytemuck::cast_slice(values).to_vec()))
}

/// The tensor as a dictionary, if that is smaller than f32.
fn encode_dictionary(values: &[f32]) -> Option<(Encoding, Vec<u8>)> {
    let (distinct, indices) = dictionary_of(values)?;
    let bits = index_bits(distinct.len());
    let packed_bytes = (values.len() * bits as usize).div_ceil(8);
    if 4 * distinct.len() + packed_bytes >= 4 * values.len() {
        return None;
    }
    let mut bytes = Vec::with_capacity(4 * distinct.len() + packed_bytes);
    bytes.extend_from_slice(bytemuck::cast_slice(&distinct));
    let mut accumulator = 0u64;
    let mut held = 0u32;
    for &index in &indices {
        accumulator |= (index as u64) << held;
        held += bits as u32;
        while held >= 8 {
            bytes.push(accumulator as u8);
            accumulator >>= 8;
            held -= 8;
        }
    }
    if held > 0 {
        bytes.push(accumulator as u8);
    }
    Some((
        Encoding::Dictionary {
            distinct: distinct.len() as u32,
            bits,
        },
        bytes,
    ))
}

/// The bytes a tensor of `values` values takes in `encoding`, or `None`
/// for an encoding no writer makes.
fn stored_bytes(encoding: Encoding, values: usize) -> Option<u64> {
    match encoding {
        Encoding::F32 => (values as u64).checked_mul(4),
        Encoding::Dictionary { distinct, bits } => {
            let distinct = distinct as usize;
            if distinct == 0 || distinct > MAX_DICTIONARY || bits != index_bits(distinct) {
                return None;
            }
            let packed = (values as u64).checked_mul(bits as u64)?.div_ceil(8);
            packed.checked_add(4 * distinct as u64)
        }
        Encoding::Sparse { nonzero } => {
            if nonzero > values as u64 {
                return None;
            }
            (values as u64)
                .div_ceil(8)
                .checked_add(nonzero.checked_mul(4)?)
        }
    }
}

/// Decodes a sparse tensor whose size has been checked.
fn decode_sparse(bytes: &[u8], values: usize, nonzero: usize) -> Result<Vec<f32>, String> {
    let (mask, stored) = bytes.split_at(values.div_ceil(8));
    let set: usize = mask.iter().map(|b| b.count_ones() as usize).sum();
    // Bits past the last value must be clear, and the count must match.
    if set != nonzero
        || (!values.is_multiple_of(8) && mask.last().is_some_and(|b| b >> (values % 8) != 0))
    {
        return Err(format!(
            "its mask marks {set} values, its table says {nonzero}"
        ));
    }
    let mut next = stored
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
    Ok((0..values)
        .map(|i| {
            if mask[i / 8] >> (i % 8) & 1 == 1 {
                next.next().unwrap_or(0.0)
            } else {
                0.0
            }
        })
        .collect())
}

/// Decodes a dictionary-coded tensor whose size has been checked.
fn decode_dictionary(
    bytes: &[u8],
    values: usize,
    distinct: usize,
    bits: u8,
) -> Result<Vec<f32>, String> {
    let (table, packed) = bytes.split_at(4 * distinct);
    let table: Vec<f32> = table
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let mask = (1u64 << bits) - 1;
    let mut out = Vec::with_capacity(values);
    let mut accumulator = 0u64;
    let mut held = 0u32;
    let mut next = packed.iter();
    for _ in 0..values {
        while held < bits as u32 {
            let byte = *next.next().ok_or("the indices end early")?;
            accumulator |= (byte as u64) << held;
            held += 8;
        }
        let index = (accumulator & mask) as usize;
        accumulator >>= bits;
        held -= bits as u32;
        out.push(
            *table
                .get(index)
                .ok_or_else(|| format!("index {index} past its {distinct} values"))?,
        );
    }
    Ok(out)
}

/// The first value of `values` that is not finite, as "NaN at index 12".
fn first_non_finite(values: &[f32]) -> Option<String> {
    let index = values.iter().position(|v| !v.is_finite())?;
    Some(format!("{} at index {index}", values[index]))
}

/// The largest decoded tensor the reader accepts (16 G values, 64 GB): a
/// sanity bound beside the file-size check every tensor passes.
const MAX_TENSOR_VALUES: usize = 1 << 34;

impl Checkpoint {
    pub fn tensor(&self, name: &str) -> Option<&[f32]> {
        self.tensors
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, values)| values.as_slice())
    }

    /// The first tensor holding a value that is not finite, as an error
    /// message, or `None` when every value is finite. A model with NaN or
    /// infinite parameters renders nothing useful and never recovers.
    pub fn non_finite(&self) -> Option<String> {
        self.tensors.iter().find_map(|(name, values)| {
            first_non_finite(values).map(|at| format!("tensor `{name}` holds {at}"))
        })
    }

    /// Writes to `path` through a temporary file in the same folder and a
    /// rename, so readers see either the old file or the complete new one.
    /// A checkpoint with a value that is not finite is refused: it would
    /// replace the last good one with a model that cannot be used.
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        let io = |problem: String| CheckpointError::Io {
            path: path.to_path_buf(),
            problem,
        };
        if let Some(problem) = self.non_finite() {
            return Err(CheckpointError::NonFinite {
                path: path.to_path_buf(),
                problem: format!(
                    "not saved: {problem} (the training has diverged); the checkpoint \
                     already there is kept"
                ),
            });
        }
        let encoded: Vec<(Encoding, Vec<u8>)> = self
            .tensors
            .iter()
            .map(|(_, values)| encode(values))
            .collect();
        let stored = StoredHeader {
            header: self.header.clone(),
            tensors: self
                .tensors
                .iter()
                .zip(&encoded)
                .map(|((name, values), (encoding, bytes))| StoredTensor {
                    name: name.clone(),
                    values: values.len(),
                    encoding: *encoding,
                    bytes: bytes.len() as u64,
                    crc32c: crate::crc32c::crc32c(bytes),
                })
                .collect(),
        };
        let header = serde_json::to_vec(&stored).map_err(|e| io(e.to_string()))?;
        crate::files::write_atomically(path, |out| {
            out.write_all(MAGIC)?;
            out.write_all(&FORMAT_VERSION.to_le_bytes())?;
            out.write_all(&(header.len() as u64).to_le_bytes())?;
            out.write_all(&header)?;
            out.write_all(&crate::crc32c::crc32c(&header).to_le_bytes())?;
            for (_, bytes) in &encoded {
                out.write_all(bytes)?;
            }
            Ok(())
        })
        .map_err(|e| io(format!("cannot write checkpoint: {e}")))
    }

    /// The header alone (what the trainer stored), without reading or
    /// checking the tensors.
    pub fn load_header(path: &Path) -> Result<serde_json::Value, CheckpointError> {
        let mut reader = Reader::open(path)?;
        Ok(reader.table()?.0)
    }

    /// Reads a checkpoint, checking every checksum (files of format 2) and
    /// that every value is finite; errors name the tensor at fault. The
    /// memory its table asks for is checked against what the machine has
    /// before any tensor is decoded; [`Self::load_for`] checks it against
    /// what a model needs.
    pub fn load(path: &Path) -> Result<Self, CheckpointError> {
        Self::load_checked(path, None)
    }

    /// [`Self::load`] for a model that holds exactly `needed` tensors (name
    /// and values, as its own [`crate::model::RadianceModel::save`] lists
    /// them): the file's table is matched against them before a tensor is
    /// decoded, and the file's size against what such a checkpoint can
    /// take, so a damaged or crafted length (a tensor stored as a hole in a
    /// sparse file) is refused by name instead of allocated. A needed
    /// tensor the file lacks is left to the model to name.
    pub fn load_for(path: &Path, needed: &[(String, usize)]) -> Result<Self, CheckpointError> {
        Self::load_checked(path, Some(needed))
    }

    fn load_checked(
        path: &Path,
        needed: Option<&[(String, usize)]>,
    ) -> Result<Self, CheckpointError> {
        let mut reader = Reader::open(path)?;
        let (header, tensors) = reader.table()?;
        if let Some(needed) = needed {
            reader.check_against(&tensors, needed)?;
        }
        let decoded_bytes = tensors.iter().fold(0u64, |sum, t| {
            sum.saturating_add((t.values as u64).saturating_mul(4))
        });
        crate::files::check_memory("loading its tensors", decoded_bytes)
            .map_err(|problem| reader.io(format!("cannot load the checkpoint: {problem}")))?;
        let mut loaded = Vec::with_capacity(tensors.len());
        for entry in tensors {
            let values = reader.tensor(&entry)?;
            if let Some(at) = first_non_finite(&values) {
                return Err(CheckpointError::NonFinite {
                    path: path.to_path_buf(),
                    problem: format!(
                        "tensor `{}` holds {at}: the model it saved had diverged and \
                         cannot be used; train again from an earlier checkpoint or anew",
                        entry.name
                    ),
                });
            }
            loaded.push((entry.name, values));
        }
        Ok(Self {
            header,
            tensors: loaded,
        })
    }
}

/// A checkpoint file being read: its version and the bytes left.
struct Reader {
    path: PathBuf,
    input: BufReader<File>,
    version: u32,
    /// The file's size.
    length: u64,
    remaining: u64,
}

impl Reader {
    fn format(&self, problem: &str) -> CheckpointError {
        CheckpointError::Format {
            path: self.path.clone(),
            problem: problem.to_string(),
        }
    }

    fn truncated(&self, problem: &str) -> CheckpointError {
        CheckpointError::Truncated {
            path: self.path.clone(),
            problem: problem.to_string(),
        }
    }

    fn damaged(&self, problem: String) -> CheckpointError {
        CheckpointError::Damaged {
            path: self.path.clone(),
            problem,
        }
    }

    /// A table unlike the model's; `problem` is the whole message after
    /// the path.
    fn other_model(&self, problem: String) -> CheckpointError {
        CheckpointError::OtherModel {
            path: self.path.clone(),
            problem,
        }
    }

    fn io(&self, problem: String) -> CheckpointError {
        CheckpointError::Io {
            path: self.path.clone(),
            problem,
        }
    }

    fn open(path: &Path) -> Result<Self, CheckpointError> {
        // A regular file only, checked on the open descriptor: a named
        // pipe would block the reader forever, a device such as /dev/zero
        // would be read until memory ran out, and a folder deserves its
        // own words rather than "file too short".
        let (file, file_length) =
            crate::files::open_regular(path).map_err(|problem| CheckpointError::Io {
                path: path.to_path_buf(),
                problem: format!("cannot read the checkpoint: {problem}"),
            })?;
        // Lengths read from the file are checked against what it holds
        // before anything is allocated for them: a damaged length must give
        // an error, not an allocation failure that aborts the process.
        let mut reader = Self {
            path: path.to_path_buf(),
            input: BufReader::new(file),
            version: 0,
            length: file_length,
            remaining: file_length.saturating_sub(20),
        };
        let mut magic = [0u8; 8];
        reader
            .input
            .read_exact(&mut magic)
            .map_err(|_| reader.format("file too short"))?;
        if &magic != MAGIC {
            return Err(reader.format("wrong magic bytes"));
        }
        let mut word = [0u8; 4];
        reader
            .input
            .read_exact(&mut word)
            .map_err(|_| reader.truncated("file too short"))?;
        reader.version = u32::from_le_bytes(word);
        if !(1..=FORMAT_VERSION).contains(&reader.version) {
            return Err(reader.format(&format!(
                "format version {}, this zrak reads 1 to {FORMAT_VERSION}",
                reader.version
            )));
        }
        Ok(reader)
    }

    /// The header and the tensors' table of contents.
    fn table(&mut self) -> Result<(serde_json::Value, Vec<StoredTensor>), CheckpointError> {
        let mut long = [0u8; 8];
        self.input
            .read_exact(&mut long)
            .map_err(|_| self.truncated("file too short"))?;
        let header_length = u64::from_le_bytes(long);
        if header_length > self.remaining.min(64 << 20) {
            let problem = format!("header length {header_length} is more than the file holds");
            // A length zrak writes, in a file that ends too soon: cut off.
            return Err(if header_length <= 64 << 20 {
                self.truncated(&problem)
            } else {
                self.format(&problem)
            });
        }
        self.remaining -= header_length;
        let mut header = vec![0u8; header_length as usize];
        self.input
            .read_exact(&mut header)
            .map_err(|_| self.truncated("truncated header"))?;
        if self.version == 1 {
            let stored: StoredHeaderV1 = serde_json::from_slice(&header)
                .map_err(|e| self.format(&format!("bad header: {e}")))?;
            let tensors = stored
                .tensors
                .into_iter()
                .map(|(name, values)| StoredTensor {
                    name,
                    values,
                    encoding: Encoding::F32,
                    bytes: (values as u64).saturating_mul(4),
                    crc32c: 0,
                })
                .collect();
            return Ok((stored.header, tensors));
        }
        let mut word = [0u8; 4];
        self.input
            .read_exact(&mut word)
            .map_err(|_| self.truncated("truncated header"))?;
        self.remaining = self.remaining.saturating_sub(4);
        let stored_crc = u32::from_le_bytes(word);
        let crc = crate::crc32c::crc32c(&header);
        if crc != stored_crc {
            return Err(self.damaged(format!(
                "its header fails its checksum (CRC-32C {crc:08x}, stored {stored_crc:08x})"
            )));
        }
        let stored: StoredHeader = serde_json::from_slice(&header)
            .map_err(|e| self.format(&format!("bad header: {e}")))?;
        Ok((stored.header, stored.tensors))
    }

    /// Refuses a table that is not the one a model holding `needed`
    /// tensors writes: a tensor it does not have, one of another length,
    /// one listed twice, or a file larger than such a checkpoint can be.
    /// Nothing is decoded before this passes.
    fn check_against(
        &self,
        tensors: &[StoredTensor],
        needed: &[(String, usize)],
    ) -> Result<(), CheckpointError> {
        let mut seen: Vec<&str> = Vec::with_capacity(tensors.len());
        for entry in tensors {
            let name = entry.name.as_str();
            let Some((_, values)) = needed.iter().find(|(n, _)| n == name) else {
                return Err(self.other_model(format!(
                    "not a zrak checkpoint (it holds a tensor `{name}` that this run's model \
                     does not have (it has {}))",
                    needed
                        .iter()
                        .map(|(n, _)| format!("`{n}`"))
                        .collect::<Vec<_>>()
                        .join(", ")
                )));
            };
            if entry.values != *values {
                return Err(self.other_model(format!(
                    "the checkpoint is damaged: tensor `{name}` is listed with {} values where \
                     this run's model has {values} (the file is damaged, or holds another model \
                     than run.json names)",
                    entry.values
                )));
            }
            if seen.contains(&name) {
                return Err(self.damaged(format!("tensor `{name}` is listed twice")));
            }
            seen.push(name);
        }
        // Each tensor's stored form is at most its values as f32 (the
        // writer keeps the smallest encoding), after the table and its
        // checksum: a larger file is padded or holed.
        let most = needed
            .iter()
            .fold(self.length - self.remaining, |sum, (_, values)| {
                sum.saturating_add((*values as u64).saturating_mul(4))
            });
        if self.length > most {
            return Err(self.damaged(format!(
                "it is {} where a checkpoint of this run's model is at most {}",
                crate::files::human_bytes(self.length),
                crate::files::human_bytes(most)
            )));
        }
        Ok(())
    }

    /// One tensor's values, checked against its checksum.
    fn tensor(&mut self, entry: &StoredTensor) -> Result<Vec<f32>, CheckpointError> {
        let name = &entry.name;
        let expected = stored_bytes(entry.encoding, entry.values)
            .filter(|&b| b == entry.bytes && entry.values <= MAX_TENSOR_VALUES);
        let Some(bytes) = expected else {
            return Err(self.format(&format!(
                "tensor `{name}`: {} values do not fit {} bytes as {:?}",
                entry.values, entry.bytes, entry.encoding
            )));
        };
        if bytes > self.remaining {
            return Err(self.truncated(&format!(
                "truncated in tensor `{name}` ({} values, {} bytes left)",
                entry.values, self.remaining
            )));
        }
        self.remaining -= bytes;
        let path = self.path.clone();
        let truncated = |_| CheckpointError::Truncated {
            path: path.clone(),
            problem: format!("truncated in tensor `{name}`"),
        };
        let (values, crc) = match entry.encoding {
            Encoding::F32 => {
                let mut values = vec![0f32; entry.values];
                self.input
                    .read_exact(bytemuck::cast_slice_mut(&mut values))
                    .map_err(truncated)?;
                let crc = crate::crc32c::crc32c(bytemuck::cast_slice(&values));
                (values, crc)
            }
            Encoding::Dictionary { .. } | Encoding::Sparse { .. } => {
                let mut stored = vec![0u8; bytes as usize];
                self.input.read_exact(&mut stored).map_err(truncated)?;
                let crc = crate::crc32c::crc32c(&stored);
                if self.version >= 2 && crc != entry.crc32c {
                    return Err(self.damaged(format!(
                        "tensor `{name}` fails its checksum (CRC-32C {crc:08x}, stored {:08x})",
                        entry.crc32c
                    )));
                }
                let values = match entry.encoding {
                    Encoding::Dictionary { distinct, bits } => {
                        decode_dictionary(&stored, entry.values, distinct as usize, bits)
                    }
                    Encoding::Sparse { nonzero } => {
                        decode_sparse(&stored, entry.values, nonzero as usize)
                    }
                    Encoding::F32 => Ok(stored
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                        .collect()),
                }
                .map_err(|e| self.damaged(format!("tensor `{name}`: {e}")))?;
                (values, crc)
            }
        };
        if self.version >= 2 && crc != entry.crc32c {
            return Err(self.damaged(format!(
                "tensor `{name}` fails its checksum (CRC-32C {crc:08x}, stored {:08x})",
                entry.crc32c
            )));
        }
        Ok(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        Checkpoint {
            header: serde_json::json!({"model": "ngp", "step": 42}),
            tensors: vec![
                ("weights".into(), vec![1.0, -2.5, f32::MIN_POSITIVE, 3e30]),
                ("empty".into(), vec![]),
            ],
        }
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap(), sample());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_non_finite_value_is_refused_and_the_previous_checkpoint_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        let mut diverged = sample();
        diverged.tensors[0].1[2] = f32::NAN;
        let error = diverged.save(&path).unwrap_err().to_string();
        assert!(
            error.contains("checkpoint.zrak")
                && error.contains("tensor `weights` holds NaN at index 2")
                && error.contains("kept"),
            "{error}"
        );
        assert_eq!(Checkpoint::load(&path).unwrap(), sample());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// Bytes of a version 1 file (before checksums) holding `checkpoint`.
    fn version_1_bytes(checkpoint: &Checkpoint) -> Vec<u8> {
        let table = serde_json::json!({
            "header": checkpoint.header,
            "tensors": checkpoint
                .tensors
                .iter()
                .map(|(name, values)| serde_json::json!([name, values.len()]))
                .collect::<Vec<_>>(),
        });
        let header = serde_json::to_vec(&table).unwrap();
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&1u32.to_le_bytes());
        bytes.extend_from_slice(&(header.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&header);
        for (_, values) in &checkpoint.tensors {
            bytes.extend_from_slice(bytemuck::cast_slice(values));
        }
        bytes
    }

    #[test]
    fn version_1_checkpoints_still_load_and_non_finite_ones_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        std::fs::write(&path, version_1_bytes(&sample())).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap(), sample());
        let mut diverged = sample();
        diverged.tensors[0].1[1] = f32::INFINITY;
        std::fs::write(&path, version_1_bytes(&diverged)).unwrap();
        let error = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(
            error.contains("tensor `weights` holds inf at index 1"),
            "{error}"
        );
    }

    #[test]
    fn a_flipped_bit_anywhere_is_found_and_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        let checkpoint = Checkpoint {
            header: serde_json::json!({"step": 7}),
            tensors: vec![
                ("params".into(), (0..100).map(|i| i as f32 * 0.25).collect()),
                (
                    "adam.m_norm".into(),
                    (0..100).map(|i| (i % 3) as f32).collect(),
                ),
            ],
        };
        checkpoint.save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header_length = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
        let data = 20 + header_length + 4;
        // One value of `params` (raw f32), then one index of the dictionary.
        for (offset, tensor) in [
            (data + 4 * 10 + 1, "params"),
            (bytes.len() - 3, "adam.m_norm"),
        ] {
            let mut damaged = bytes.clone();
            damaged[offset] ^= 0x10;
            std::fs::write(&path, &damaged).unwrap();
            let error = Checkpoint::load(&path).unwrap_err().to_string();
            assert!(
                error.contains("damaged")
                    && error.contains(&format!("tensor `{tensor}` fails its checksum")),
                "{error}"
            );
        }
        let mut damaged = bytes.clone();
        damaged[25] ^= 0x01;
        std::fs::write(&path, &damaged).unwrap();
        let error = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(error.contains("header fails its checksum"), "{error}");
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap(), checkpoint);
    }

    #[test]
    fn tensors_of_few_values_are_stored_as_a_dictionary_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        let n = 10_000;
        let values_of = |distinct: usize| -> Vec<f32> {
            (0..n)
                .map(|i| match (i * 7919) % distinct {
                    0 => -0.0,
                    1 => f32::from_bits(u32::MAX),
                    k => k as f32 * 0.5,
                })
                .collect()
        };
        for distinct in [1, 2, 3, 255, 256, 257, 5000] {
            let values: Vec<f32> = if distinct == 1 {
                vec![-1.0; n]
            } else {
                values_of(distinct)
            };
            let (encoding, stored) = encode(&values);
            let bits = index_bits(distinct);
            assert_eq!(
                encoding,
                Encoding::Dictionary {
                    distinct: distinct as u32,
                    bits
                }
            );
            assert_eq!(stored.len(), 4 * distinct + (n * bits as usize).div_ceil(8));
            let decoded = decode_dictionary(&stored, n, distinct, bits).unwrap();
            let same = decoded
                .iter()
                .zip(&values)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{distinct} values");
        }
        // A tensor mostly +0.0 (untouched moments) keeps a bit a value and
        // the others; -0.0 is not +0.0.
        let mostly_zero: Vec<f32> = (0..100_000)
            .map(|i| match i % 97 {
                0 => i as f32 * 1e-3 + 1.0,
                1 => -0.0,
                _ => 0.0,
            })
            .collect();
        let (encoding, stored) = encode(&mostly_zero);
        let nonzero = 2 * 100_000 / 97 + 1;
        assert_eq!(
            encoding,
            Encoding::Sparse {
                nonzero: nonzero as u64
            }
        );
        assert_eq!(stored.len(), 12_500 + 4 * nonzero);
        let decoded = decode_sparse(&stored, 100_000, nonzero).unwrap();
        assert!(
            decoded
                .iter()
                .zip(&mostly_zero)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        // A tensor of many values stays f32.
        let many: Vec<f32> = (0..100_000).map(|i| i as f32).collect();
        assert_eq!(encode(&many).0, Encoding::F32);
        let checkpoint = Checkpoint {
            header: serde_json::json!({}),
            tensors: vec![("grid".into(), vec![-1.0; 1 << 16]), ("many".into(), many)],
        };
        checkpoint.save(&path).unwrap();
        // The untrained grid takes a bit a cell, not 32.
        let size = std::fs::metadata(&path).unwrap().len();
        assert!(size < 400_000 + (1 << 13) + 1000, "{size}");
        assert_eq!(Checkpoint::load(&path).unwrap(), checkpoint);
    }

    /// What `sample` holds, as a model would list it.
    fn sample_needs() -> Vec<(String, usize)> {
        sample()
            .tensors
            .iter()
            .map(|(name, values)| (name.clone(), values.len()))
            .collect()
    }

    #[test]
    fn a_table_unlike_the_models_is_refused_before_any_tensor_is_decoded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        assert_eq!(
            Checkpoint::load_for(&path, &sample_needs()).unwrap(),
            sample()
        );
        // Another length than the model's.
        let mut needs = sample_needs();
        needs[0].1 = 5;
        let error = Checkpoint::load_for(&path, &needs).unwrap_err();
        assert!(
            matches!(error, CheckpointError::OtherModel { .. }),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.ends_with(
                "checkpoint.zrak: the checkpoint is damaged: tensor `weights` is listed with 4 \
                 values where this run's model has 5 (the file is damaged, or holds another \
                 model than run.json names)"
            ),
            "{error}"
        );
        assert!(
            error.contains("checkpoint.zrak")
                && error.contains(
                    "tensor `weights` is listed with 4 values where this run's model has 5"
                ),
            "{error}"
        );
        // A tensor the model does not have.
        let error = Checkpoint::load_for(&path, &sample_needs()[..1]).unwrap_err();
        assert!(
            matches!(error, CheckpointError::OtherModel { .. }),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.ends_with(
                "checkpoint.zrak: not a zrak checkpoint (it holds a tensor `empty` that this \
                 run's model does not have (it has `weights`))"
            ),
            "{error}"
        );
        // A file longer than such a checkpoint can be (a hole after it).
        let length = std::fs::metadata(&path).unwrap().len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .unwrap()
            .set_len(length + (1 << 30))
            .unwrap();
        let error = Checkpoint::load_for(&path, &sample_needs()).unwrap_err();
        assert!(
            matches!(error, CheckpointError::Damaged { .. }),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.contains("where a checkpoint of this run's model is at most"),
            "{error}"
        );
    }

    #[test]
    fn a_tensor_stored_as_a_hole_is_refused_by_name_not_allocated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        // `weights` claims 2^36 f32 values (256 GiB), and the file's size,
        // mostly a hole, vouches for them.
        let values = 1usize << 36;
        let stored = StoredHeader {
            header: serde_json::json!({}),
            tensors: vec![StoredTensor {
                name: "weights".into(),
                values,
                encoding: Encoding::F32,
                bytes: 4 * values as u64,
                crc32c: 0,
            }],
        };
        let header = serde_json::to_vec(&stored).unwrap();
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(header.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&header);
        bytes.extend_from_slice(&crate::crc32c::crc32c(&header).to_le_bytes());
        std::fs::write(&path, &bytes).unwrap();
        let file = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        if file
            .set_len(bytes.len() as u64 + 4 * values as u64)
            .is_err()
        {
            // A file system without sparse files this large: nothing to test.
            return;
        }
        drop(file);
        let error = Checkpoint::load_for(&path, &[("weights".into(), 1000)])
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("tensor `weights` is listed with 68719476736 values"),
            "{error}"
        );
        // Without a model to match, the memory it asks for is refused.
        if crate::files::available_memory().is_some() {
            let error = Checkpoint::load(&path).unwrap_err().to_string();
            assert!(
                error.contains(
                    "cannot load the checkpoint: loading its tensors needs about 274.9 GB"
                ),
                "{error}"
            );
        }
    }

    #[cfg(unix)]
    #[test]
    fn a_folder_or_a_pipe_named_checkpoint_is_refused_for_what_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        std::fs::create_dir(&path).unwrap();
        let error = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(
            error.contains("checkpoint.zrak: cannot read the checkpoint: a folder, not a file"),
            "{error}"
        );
        std::fs::remove_dir(&path).unwrap();
        let name = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
        let error = Checkpoint::load_header(&path).unwrap_err().to_string();
        assert!(error.contains("named pipe"), "{error}");
    }

    #[test]
    fn truncated_or_foreign_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let error = Checkpoint::load(&path).unwrap_err();
        assert!(
            matches!(error, CheckpointError::Truncated { .. }),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.contains("checkpoint.zrak: not a zrak checkpoint (truncated in tensor `weights`"),
            "{error}"
        );
        // Cut within the header.
        std::fs::write(&path, &bytes[..30]).unwrap();
        let error = Checkpoint::load(&path).unwrap_err();
        assert!(
            matches!(error, CheckpointError::Truncated { .. }),
            "{error:?}"
        );
        std::fs::write(&path, b"PNG and other things").unwrap();
        let error = Checkpoint::load(&path).unwrap_err();
        assert!(matches!(error, CheckpointError::Format { .. }), "{error:?}");
        let error = error.to_string();
        assert!(error.contains("not a zrak checkpoint"), "{error}");
    }
}
