//! Scene files and images that are not what they claim (issue 43): an
//! image too large to decode in the memory there is, a name in another
//! Unicode normalisation, a folder, pipe or device where an image should
//! be, a split file that is a link looping onto itself, control characters
//! in a `file_path`. Each is refused by `zrak info` with a sentence naming
//! the file and the problem, never a panic, an abort or a silent success.

use std::path::Path;
use std::process::{Command, Output, Stdio};

use serde_json::{Value, json};
use zrak::scene::ImageRgba8;

use crate::common;

fn frame(file_path: &str) -> Value {
    let identity = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
    json!({ "file_path": file_path, "transform_matrix": identity })
}

fn write_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    ImageRgba8::new(4, 4, vec![200; 64]).save_png(path).unwrap();
}

/// A NeRF-synthetic scene in `root` whose `transforms_train.json` lists
/// `file_paths`, which the caller provides (or leaves broken).
fn write_split(root: &Path, split: &str, file_paths: &[&str]) {
    std::fs::create_dir_all(root).unwrap();
    let frames: Vec<Value> = file_paths.iter().map(|p| frame(p)).collect();
    let file = json!({ "camera_angle_x": 0.69, "frames": frames });
    std::fs::write(
        root.join(format!("transforms_{split}.json")),
        file.to_string(),
    )
    .unwrap();
}

/// Runs `zrak info SCENE` in `dir` with standard input closed, returning
/// its output.
fn info(dir: &Path, scene: &str) -> Output {
    Command::new(common::zrak_bin())
        .args(["info", scene])
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("the zrak binary starts")
}

/// `zrak info SCENE`'s standard error, which must come with exit status 1
/// (an error zrak reports, not a panic's 101 or an abort's signal).
fn refused(dir: &Path, scene: &str) -> String {
    let output = info(dir, scene);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(
        output.status.code(),
        Some(1),
        "zrak info {scene} should fail with status 1 ({}):\nstdout:\n{}\nstderr:\n{stderr}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    stderr
}

#[track_caller]
fn assert_mentions(message: &str, parts: &[&str]) {
    for part in parts {
        assert!(
            message.contains(part),
            "{message:?} does not mention {part:?}"
        );
    }
}

// ---------------------------------------------------------------------
// An image larger than the memory there is to decode it.
// ---------------------------------------------------------------------

/// Bits written least significant first, as deflate packs them.
#[derive(Default)]
struct BitWriter {
    bytes: Vec<u8>,
    pending: u64,
    count: u32,
}

impl BitWriter {
    fn bits(&mut self, value: u32, count: u32) {
        self.pending |= u64::from(value) << self.count;
        self.count += count;
        while self.count >= 8 {
            self.bytes.push(self.pending as u8);
            self.pending >>= 8;
            self.count -= 8;
        }
    }

    /// A Huffman code, which deflate stores most significant bit first.
    fn code(&mut self, code: u32, length: u32) {
        self.bits(code.reverse_bits() >> (32 - length), length);
    }

    fn finish(mut self) -> Vec<u8> {
        if self.count > 0 {
            self.bytes.push(self.pending as u8);
        }
        self.bytes
    }
}

fn crc32(parts: &[&[u8]]) -> u32 {
    let table: Vec<u32> = (0..256u32)
        .map(|n| {
            (0..8).fold(n, |c, _| {
                if c & 1 == 1 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                }
            })
        })
        .collect();
    let mut crc = !0u32;
    for byte in parts.iter().flat_map(|p| p.iter()) {
        crc = table[((crc ^ u32::from(*byte)) & 0xFF) as usize] ^ (crc >> 8);
    }
    !crc
}

/// A valid PNG of `width`×`height` black 8-bit grey pixels, made without
/// ever holding its pixels: its zlib stream is written by hand as one
/// literal zero and then copies of 258 zeros each (deflate's fixed codes),
/// so a 30000×30000 image, 900 MB of pixels, is a 5.7 MB file made in
/// moments. (An encoder would need the 900 MB first.)
fn write_black_png(path: &Path, width: u32, height: u32) {
    let raw_bytes = u64::from(height) * (u64::from(width) + 1);
    let mut deflate = BitWriter::default();
    deflate.bits(1, 1); // the last block
    deflate.bits(1, 2); // fixed Huffman codes
    deflate.code(0x30, 8); // literal 0
    let after_first = raw_bytes - 1;
    for _ in 0..after_first / 258 {
        deflate.code(0xC5, 8); // length 258 (symbol 285)
        deflate.code(0, 5); // distance 1
    }
    for _ in 0..after_first % 258 {
        deflate.code(0x30, 8);
    }
    deflate.code(0, 7); // end of block
    let mut zlib = vec![0x78, 0x01];
    zlib.extend(deflate.finish());
    // Adler-32 of zeros: the sum of bytes stays 1, the sum of sums grows
    // by 1 per byte.
    let adler = (((raw_bytes % 65521) as u32) << 16) | 1;
    zlib.extend(adler.to_be_bytes());

    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        png.extend((data.len() as u32).to_be_bytes());
        png.extend(kind);
        png.extend(data);
        png.extend(crc32(&[kind, data]).to_be_bytes());
    };
    let mut header = Vec::new();
    header.extend(width.to_be_bytes());
    header.extend(height.to_be_bytes());
    header.extend([8, 0, 0, 0, 0]); // 8-bit grey, deflate, no interlace
    chunk(b"IHDR", &header);
    chunk(b"IDAT", &zlib);
    chunk(b"IEND", &[]);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, png).unwrap();
}

/// The hand-made PNG is one a decoder reads: the refusal below is of a
/// real image, not of a broken file.
#[test]
fn the_hand_made_png_decodes() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("black.png");
    write_black_png(&path, 301, 7);
    let loaded = zrak::scene::load_image(&path).unwrap();
    assert_eq!((loaded.image.width, loaded.image.height), (301, 7));
    assert!(loaded.image.data.chunks(4).all(|p| p == [0, 0, 0, 255]));
}

/// A 30000×30000 PNG of a few megabytes decodes to 0.9 GB of grey and
/// 3.6 GB of RGBA: under a 4 GB address-space limit `zrak info` says so,
/// naming the file, its size in pixels and the memory on both sides,
/// instead of aborting inside the decoder.
#[test]
fn an_image_too_large_for_the_memory_is_refused_by_its_size() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    write_black_png(&scene.join("train/r_0.png"), 30000, 30000);
    assert!(
        std::fs::metadata(scene.join("train/r_0.png"))
            .unwrap()
            .len()
            < 8_000_000
    );
    write_split(&scene, "train", &["./train/r_0"]);
    let output = Command::new("sh")
        .args(["-c", "ulimit -v 4000000 && exec \"$0\" info scene"])
        .arg(common::zrak_bin())
        .current_dir(dir.path())
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{}: {stderr}", output.status);
    assert_mentions(
        &stderr,
        &[
            "train/r_0.png",
            "30000×30000 pixels, which need about 4.5 GB of memory to decode, more than the",
            "available",
            "make the image smaller",
        ],
    );
}

// ---------------------------------------------------------------------
// Names that lead nowhere, or somewhere that is not an image.
// ---------------------------------------------------------------------

/// `file_path` spells "café" precomposed (NFC, as a Linux editor writes
/// it); the file on disk spells it as "e" and a combining accent (NFD, as
/// macOS stores names). "not found" then names the file that is there.
#[test]
fn an_image_named_in_another_normalisation_is_pointed_out() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    write_png(&scene.join("train/cafe\u{301}.png"));
    write_split(&scene, "train", &["./train/caf\u{e9}"]);
    let stderr = refused(dir.path(), "scene");
    assert_mentions(
        &stderr,
        &[
            "transforms_train.json: frame 0",
            "image file not found",
            "caf\u{e9}.png",
            "holds \"cafe\u{301}.png\"",
            "(Unicode NFD)",
            "(Unicode NFC)",
            "rename the file",
        ],
    );
}

/// A folder and a named pipe called `r_0.png`, where `file_path` says
/// `./train/r_0`: each is named for what it is, not "not found", and the
/// pipe is not waited on.
#[test]
fn a_folder_or_pipe_named_like_the_image_is_named_for_what_it_is() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let folder_scene = dir.path().join("folder");
    std::fs::create_dir_all(folder_scene.join("train/r_0.png")).unwrap();
    write_split(&folder_scene, "train", &["./train/r_0"]);
    let stderr = refused(dir.path(), "folder");
    assert_mentions(
        &stderr,
        &[
            "frame 0",
            "train/r_0.png, which is a folder, not a file",
            "`file_path` must name a PNG or JPEG file",
        ],
    );
    assert!(!stderr.contains("not found"), "{stderr}");

    let pipe_scene = dir.path().join("pipe");
    std::fs::create_dir_all(pipe_scene.join("train")).unwrap();
    let fifo = std::ffi::CString::new(
        pipe_scene
            .join("train/r_0.png")
            .into_os_string()
            .into_encoded_bytes(),
    )
    .unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
    write_split(&pipe_scene, "train", &["./train/r_0"]);
    let started = std::time::Instant::now();
    let stderr = refused(dir.path(), "pipe");
    assert!(started.elapsed().as_secs() < 20, "the pipe was waited on");
    assert_mentions(
        &stderr,
        &["train/r_0.png, which is a named pipe (FIFO), not a file"],
    );
    assert!(!stderr.contains("not found"), "{stderr}");
}

/// A `transforms_train.json` that is a symbolic link to itself, beside a
/// good `transforms_val.json`: an error naming the file, not a scene with
/// no training views and exit status 0.
#[test]
fn a_split_file_linking_to_itself_is_an_error() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    write_png(&scene.join("val/r_0.png"));
    write_split(&scene, "val", &["./val/r_0"]);
    std::os::unix::fs::symlink("transforms_train.json", scene.join("transforms_train.json"))
        .unwrap();
    let stderr = refused(dir.path(), "scene");
    assert_mentions(
        &stderr,
        &[
            "transforms_train.json",
            "a symbolic link that loops",
            "replace the link with the JSON file itself, or remove it",
        ],
    );
}

/// Control characters in a `file_path` (a NUL, an escape sequence that
/// would clear the terminal) are shown escaped, never written raw.
#[test]
fn control_characters_in_a_file_path_are_escaped() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let nul = dir.path().join("nul");
    write_png(&nul.join("train/r_0.png"));
    write_split(&nul, "train", &["./train/r_0", "./train/r\u{0}_1"]);
    let stderr = refused(dir.path(), "nul");
    assert_mentions(
        &stderr,
        &[
            "frame 1",
            r#""./train/r\0_1" holds a NUL character"#,
            "write the image's path there",
        ],
    );
    let escape = dir.path().join("escape");
    write_split(&escape, "train", &["./train/r\u{1b}[2J_0.png"]);
    let stderr = refused(dir.path(), "escape");
    assert_mentions(&stderr, &["image file not found", r"r\u{1b}[2J_0.png"]);
    for stderr in [&refused(dir.path(), "nul"), &stderr] {
        assert!(
            !stderr.chars().any(|c| c.is_control() && c != '\n'),
            "a raw control character in {stderr:?}"
        );
    }
}

/// `file_path` `/dev/stdin`, a device here (standard input is /dev/null):
/// one plain sentence saying so, with the frame.
#[test]
fn a_device_as_file_path_is_named_a_device() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    write_png(&scene.join("train/r_0.png"));
    write_split(&scene, "train", &["./train/r_0", "/dev/stdin"]);
    let stderr = refused(dir.path(), "scene");
    assert_mentions(
        &stderr,
        &[
            "transforms_train.json: frame 1: `file_path` \"/dev/stdin\" is a device, not a \
             file: `file_path` must name a PNG or JPEG file",
        ],
    );
}
