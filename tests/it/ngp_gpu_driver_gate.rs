//! The gpu half of issue 28's gate: Instant-NGP through the generic gpu
//! driver (`GpuModel` with `GpuNgpField` and the recipe of `field::ngp`)
//! reproduces what its own driver, `GpuNgp`, produced on a fixed seed:
//! every step's loss over 20 steps (the grid's full update at step 0 and
//! its next at step 16 among them), the CRC-32C of every checkpoint tensor
//! (parameters, Adam's moments, the occupancy grid), of a rendered view's
//! pixels, of the colour image drawn into the viewer's texture and of the
//! checkpoint file's bytes apart from the format version. The record,
//! `tests/fixtures/ngp_gpu_driver.txt`, was written from `GpuNgp` on
//! lavapipe while both drivers existed (`record_the_old_driver` in this
//! file at commit da8e5bd, which also compared the two drivers' runs bit
//! for bit and loaded each one's checkpoint into the other); the same
//! checkpoint bytes mean the old driver's checkpoints load into the new.
//!
//! The hash table has 2^12 entries per level instead of 2^19 (every level
//! hashes, as the paper's finer levels do), to keep the test to a minute on
//! lavapipe. On another device than the record's (another GPU, another
//! LLVM under lavapipe) f32 sums and float atomic adds run in other orders,
//! so there the losses are compared within a tolerance
//! ([`LOSS_TOLERANCE`]). Lavapipe gave the same bits for two runs of the
//! old driver, float atomics of the hash grid's backward pass included.

use crate::common;

use std::sync::Arc;

use zrak::engine::cpu::fields::ngp::NgpShape;
use zrak::engine::cpu::hash_grid::HashGridLayout;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::render::{read_texture_rgba8, render_target};
use zrak::field::ngp::HashGridConfig;
use zrak::field::ngp::LossKind;
use zrak::model::RenderMode;
use zrak::scene::Scene;
use zrak::train::checkpoint::Checkpoint;
use zrak::train::model::{RadianceModel, RenderedPixel};
use zrak::train::trainer::Trainer;

const SEED: u64 = 7;
/// Steps compared: the grid updates at step 0 (all cells) and 16.
const STEPS: usize = 20;
/// 2^12 samples a batch: a few dozen rays on the small scene.
const BATCH_SAMPLES: usize = 1 << 12;

fn small_scene() -> Arc<Scene> {
    common::small_scene(32)
}

/// The paper's field with a 2^12-entry table per level (as
/// tests/hard_cases.rs and tests/ngp_field_gpu.rs).
fn small_shape(scene: &Scene) -> NgpShape {
    let mut shape = NgpShape::for_scene(scene);
    shape.grid = HashGridLayout::new(&HashGridConfig {
        log2_table_size: 12,
        ..HashGridConfig::paper(scene.unit_cube.aabb_scale)
    });
    shape
}

/// The test's device, shared by both drivers and the textures they draw
/// into (a context per driver, as the viewer's worker makes them).
fn shared(context: &GpuContext) -> GpuContext {
    GpuContext::from_existing(
        &context.adapter,
        context.device.clone(),
        context.queue.clone(),
    )
    .unwrap()
}

fn new_driver(scene: &Scene, context: &GpuContext) -> Box<dyn RadianceModel> {
    Box::new(
        zrak::train::gpu_ngp_with_shape(
            shared(context),
            scene,
            small_shape(scene),
            SEED,
            LossKind::Huber,
            Some(BATCH_SAMPLES),
        )
        .expect("the new driver"),
    )
}

fn render_view(model: &dyn RadianceModel, scene: &Scene) -> Vec<u32> {
    let camera = &scene.val[0].camera;
    let rays = camera.all_rays();
    let origins: Vec<_> = rays.iter().map(|r| r.origin).collect();
    let directions: Vec<_> = rays.iter().map(|r| r.direction).collect();
    let mut out = vec![RenderedPixel::default(); rays.len()];
    model.render(
        &origins,
        &directions,
        &vec![0.0; rays.len()],
        [1.0; 3],
        &mut out,
    );
    out.iter()
        .flat_map(|p| [p.rgb[0], p.rgb[1], p.rgb[2], p.opacity, p.depth])
        .map(f32::to_bits)
        .collect()
}

/// The bytes `model` draws into the viewer's texture for the first
/// validation view.
fn texture_of(
    model: &dyn RadianceModel,
    scene: &Scene,
    context: &GpuContext,
    mode: RenderMode,
) -> Vec<u8> {
    let camera = &scene.val[0].camera;
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let texture = render_target(&context.device, width, height);
    let render = model
        .texture_render()
        .expect("a gpu model draws into textures");
    render
        .render_to_texture(camera, mode, [1.0; 3], &texture)
        .unwrap();
    let bytes = read_texture_rgba8(context, &texture);
    // Not all one colour: the view shows the trained field (its depth,
    // after 20 steps, is still too faint to show).
    if mode == RenderMode::Rgb {
        assert!(
            bytes.chunks_exact(4).any(|p| p != &bytes[..4]),
            "a flat image"
        );
    }
    bytes
}

/// A checkpoint's bytes as a file holds them.
fn file_bytes(checkpoint: &Checkpoint) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.zrak");
    checkpoint.save(&path).unwrap();
    std::fs::read(path).unwrap()
}

/// What a fixed-seed run produced.
struct Run {
    losses: Vec<u32>,
    checkpoint: Checkpoint,
    pixels: Vec<u32>,
    trainer: Trainer,
}

fn run(model: Box<dyn RadianceModel>, scene: &Arc<Scene>) -> Run {
    let mut trainer = Trainer::new(model, scene.clone(), SEED);
    let losses = (0..STEPS).map(|_| trainer.step().loss.to_bits()).collect();
    Run {
        losses,
        checkpoint: trainer.model.save(),
        pixels: render_view(trainer.model.as_ref(), scene),
        trainer,
    }
}

/// Where the old driver's record lives.
const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/fixtures/ngp_gpu_driver.txt"
);

/// Relative difference allowed between a step's loss here and the
/// record's on another device than the record's (another GPU, or
/// lavapipe of another LLVM): such a device only reorders f32 sums and
/// float atomic adds (≈ 1e-7 relative each), which 20 steps keep orders of
/// magnitude below 1e-3, while a broken stage moves the losses by more (the
/// cpu gate's argument, tests/ngp_driver_gate.rs).
const LOSS_TOLERANCE: f64 = 1e-3;

/// The format version's bytes in a checkpoint file: after the 8-byte
/// magic, a little-endian u32 (src/model/checkpoint.rs).
const VERSION_BYTES: std::ops::Range<usize> = 8..12;

/// CRC-32C of `u32`s, little-endian.
fn crc_of_words(words: &[u32]) -> u32 {
    let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
    zrak::crc32c::crc32c(&bytes)
}

/// What a fixed-seed run produced, as the fixture holds it.
#[derive(Debug, Clone, PartialEq)]
struct Record {
    /// The adapter and driver the run computed on.
    device: String,
    losses: Vec<u32>,
    /// Every checkpoint tensor: name, length, CRC-32C of its bits.
    tensors: Vec<(String, usize, u32)>,
    /// CRC-32C of a validation view's pixels (colour, opacity, depth bits).
    pixels: u32,
    /// CRC-32C of the colour texture's bytes.
    texture: u32,
    /// CRC-32C of the checkpoint file's bytes, the version zeroed.
    checkpoint: u32,
}

impl Record {
    fn of(run: &Run, scene: &Scene, context: &GpuContext) -> Self {
        let mut bytes = file_bytes(&run.checkpoint);
        bytes[VERSION_BYTES].fill(0);
        Self {
            device: device_name(context),
            losses: run.losses.clone(),
            tensors: run
                .checkpoint
                .tensors
                .iter()
                .map(|(name, values)| {
                    let bits: Vec<u32> = values.iter().map(|v| v.to_bits()).collect();
                    (name.clone(), values.len(), crc_of_words(&bits))
                })
                .collect(),
            pixels: crc_of_words(&run.pixels),
            texture: zrak::crc32c::crc32c(&texture_of(
                run.trainer.model.as_ref(),
                scene,
                context,
                RenderMode::Rgb,
            )),
            checkpoint: zrak::crc32c::crc32c(&bytes),
        }
    }

    fn to_text(&self) -> String {
        let mut text = String::from(
            "# Instant-NGP through its own gpu driver (GpuNgp), seed 7, 20 steps of\n\
             # 2^12 samples on the 32-pixel demo scene, hash table 2^12 per level:\n\
             # written by record_the_old_driver in tests/it/ngp_gpu_driver_gate.rs\n\
             # while both drivers existed; CRCs are CRC-32C.\n",
        );
        text += &format!("device {}\n", self.device);
        for (step, loss) in self.losses.iter().enumerate() {
            text += &format!("loss {step} {loss:08x}\n");
        }
        for (name, len, crc) in &self.tensors {
            text += &format!("tensor {name} {len} {crc:08x}\n");
        }
        text += &format!("pixels {:08x}\n", self.pixels);
        text += &format!("texture {:08x}\n", self.texture);
        text += &format!("checkpoint {:08x}\n", self.checkpoint);
        text
    }

    fn parse(text: &str) -> Result<Self, String> {
        let hex = |s: &str| u32::from_str_radix(s, 16).map_err(|e| format!("`{s}`: {e}"));
        let mut record = Record {
            device: String::new(),
            losses: Vec::new(),
            tensors: Vec::new(),
            pixels: 0,
            texture: 0,
            checkpoint: 0,
        };
        for (number, line) in text.lines().enumerate() {
            let at = |problem: String| format!("{FIXTURE} line {}: {problem}", number + 1);
            if let Some(device) = line.strip_prefix("device ") {
                record.device = device.to_string();
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
                ["texture", crc] => record.texture = hex(crc).map_err(at)?,
                ["checkpoint", crc] => record.checkpoint = hex(crc).map_err(at)?,
                _ => return Err(at(format!("unexpected line `{line}`"))),
            }
        }
        if record.device.is_empty() || record.losses.len() != STEPS {
            return Err(format!(
                "{FIXTURE}: needs a `device` line and {STEPS} losses"
            ));
        }
        Ok(record)
    }
}

/// The adapter and its driver, as the record names them.
fn device_name(context: &GpuContext) -> String {
    format!("{} / {}", context.info.name, context.info.driver_info)
}

#[test]
fn gpu_model_reproduces_the_old_drivers_record() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let context = common::gpu_context();
    let text = std::fs::read_to_string(FIXTURE).unwrap_or_else(|e| panic!("{FIXTURE}: {e}"));
    let expected = Record::parse(&text).unwrap_or_else(|e| panic!("{e}"));
    let run = run(new_driver(&scene, &context), &scene);
    let record = Record::of(&run, &scene, &context);
    // The fixture's format reads back what it writes.
    assert_eq!(Record::parse(&record.to_text()).as_ref(), Ok(&record));
    if record.device == expected.device {
        for (step, (got, want)) in record.losses.iter().zip(&expected.losses).enumerate() {
            assert_eq!(
                got,
                want,
                "step {step}'s loss: {} here, {} recorded",
                f32::from_bits(*got),
                f32::from_bits(*want)
            );
        }
        assert_eq!(record.tensors, expected.tensors, "checkpoint tensors");
        assert_eq!(record.pixels, expected.pixels, "rendered pixels");
        assert_eq!(record.texture, expected.texture, "texture bytes");
        assert_eq!(
            record.checkpoint, expected.checkpoint,
            "checkpoint file bytes"
        );
    } else {
        eprintln!(
            "device {} here, {} in the record: losses compared within {LOSS_TOLERANCE}",
            record.device, expected.device
        );
        for (step, (got, want)) in record.losses.iter().zip(&expected.losses).enumerate() {
            let (got, want) = (f32::from_bits(*got) as f64, f32::from_bits(*want) as f64);
            assert!(
                (got - want).abs() <= LOSS_TOLERANCE * want.abs(),
                "step {step}'s loss: {got} here, {want} recorded"
            );
        }
        let names = |r: &Record| -> Vec<(String, usize)> {
            r.tensors.iter().map(|(n, l, _)| (n.clone(), *l)).collect()
        };
        assert_eq!(names(&record), names(&expected), "checkpoint tensors");
    }
}
