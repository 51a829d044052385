//! `zrak export`: a trained run's surface as a mesh (`mesh`) or its
//! training views' depths as a point cloud (`points`), PLY or OBJ files.
//! Both run on the cpu engine (they ask the model for its density and
//! colour at points, which only that engine answers), inside the run's crop
//! box when it has one.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Subcommand};
use indicatif::ProgressBar;
use zrak::engine::EngineKind;
use zrak::interrupt::note;
use zrak::mesh::extract::{
    MAX_RESOLUTION, MeshSettings, default_threshold, extract_mesh, grid_dims, mesh_bytes,
};
use zrak::mesh::points::{PointSettings, extract_points, stride_for};
use zrak::mesh::{MeshFormat, MinComponent, points_to_ply};
use zrak::scene::crop::{CropArg, CropBox};
use zrak::train::run::RunFolder;

use super::run_config::restore_run;

#[derive(Subcommand, Debug)]
pub enum ExportCommand {
    /// The density field's surface by marching cubes, with vertex colours,
    /// as a binary PLY or an OBJ file.
    Mesh(MeshArgs),
    /// A coloured point cloud at each training ray's expected depth, as a
    /// binary PLY file.
    Points(PointsArgs),
    /// The training cameras with the pose corrections the run learned
    /// (trained with camera refinement), as a transforms.json other tools
    /// read.
    Cameras(CamerasArgs),
}

#[derive(Args, Debug)]
pub struct CamerasArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    /// The transforms.json to write.
    #[arg(long)]
    out: PathBuf,
    /// Replace --out if it exists.
    #[arg(long)]
    force: bool,
}

/// The crop box argument both exports and `zrak render` take.
#[derive(Args, Debug, Clone)]
pub struct CropArgs {
    /// The crop box, `cx,cy,cz,sx,sy,sz` (centre and size in world units),
    /// optionally `,rx,ry,rz` (turned by degrees about x, y, z), saved in
    /// the run folder (crop.json) for later renders and exports; `none`
    /// removes it. Default: the run's saved box, else the whole scene.
    #[arg(long, value_name = "BOX", allow_hyphen_values = true)]
    pub crop: Option<CropArg>,
}

impl CropArgs {
    /// The crop box the command uses: `--crop` (saved in the run folder,
    /// or removed from it with `none`), else the run's saved one.
    pub fn resolve(&self, run: &Path) -> anyhow::Result<Option<CropBox>> {
        match self.crop {
            Some(CropArg::Box(crop)) => {
                CropBox::save_to_run(Some(&crop), run).map_err(anyhow::Error::msg)?;
                note(&format!(
                    "crop box saved in {} for later renders and exports (--crop none removes it)",
                    CropBox::path_in(run).display()
                ));
                Ok(Some(crop))
            }
            Some(CropArg::None) => {
                CropBox::save_to_run(None, run).map_err(anyhow::Error::msg)?;
                Ok(None)
            }
            None => {
                let saved = CropBox::load_from_run(run).map_err(anyhow::Error::msg)?;
                if saved.is_some() {
                    note(&format!(
                        "using the crop box in {} (--crop none removes it)",
                        CropBox::path_in(run).display()
                    ));
                }
                Ok(saved)
            }
        }
    }
}

#[derive(Args, Debug)]
pub struct MeshArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    /// Grid nodes along the longest side of the box meshed.
    #[arg(long, default_value_t = 256)]
    resolution: u32,
    /// The density (per world unit) the surface is drawn at (default: 30
    /// per unit-cube length, 9.9 on NeRF-synthetic's scale).
    #[arg(long)]
    threshold: Option<f32>,
    /// The file to write: .ply (binary) or .obj.
    #[arg(long)]
    out: PathBuf,
    /// Drop disconnected pieces smaller than this: a face count (500) or a
    /// share of all faces (0.01 or 1%).
    #[arg(long, value_name = "SIZE")]
    min_component: Option<MinComponent>,
    #[command(flatten)]
    crop: CropArgs,
    /// Replace --out if it exists.
    #[arg(long)]
    force: bool,
}

#[derive(Args, Debug)]
pub struct PointsArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    /// The file to write (.ply).
    #[arg(long)]
    out: PathBuf,
    /// About this many rays are cast over all training views (each view's
    /// pixels taken every n-th column and row).
    #[arg(long, default_value_t = 1_000_000)]
    max_rays: usize,
    /// Rays less opaque than this give no point.
    #[arg(long, default_value_t = 0.9)]
    min_opacity: f32,
    #[command(flatten)]
    crop: CropArgs,
    /// Replace --out if it exists.
    #[arg(long)]
    force: bool,
}

pub fn export(command: ExportCommand) -> anyhow::Result<()> {
    match command {
        ExportCommand::Mesh(args) => export_mesh(args),
        ExportCommand::Points(args) => export_points(args),
        ExportCommand::Cameras(args) => export_cameras(args),
    }
}

/// Reads the run's corrections from its checkpoint (no model is built) and
/// its training cameras from its scene at full size, whose image files the
/// transforms.json names.
fn export_cameras(args: CamerasArgs) -> anyhow::Result<()> {
    use zrak::engine::shared::camera_refinement::{VALUES_PER_IMAGE, corrected_pose};
    check_output(&args.out, args.force)?;
    let folder = RunFolder::open(&args.run).map_err(anyhow::Error::msg)?;
    let config = super::run_config::read_run_config(&folder)?;
    let path = folder.checkpoint_path();
    let checkpoint = zrak::model::checkpoint::Checkpoint::load(&path)?;
    let corrections = checkpoint.tensor("cameras").ok_or_else(|| {
        anyhow::anyhow!(
            "{}: the run did not refine its cameras (train it with camera refinement on)",
            path.display()
        )
    })?;
    let scene = super::run_config::load_run_scene(&config.scene, 1, config.training_scales)?;
    anyhow::ensure!(
        corrections.len() == VALUES_PER_IMAGE * scene.train.len(),
        "{}: {} camera corrections for {} training images of {}",
        path.display(),
        corrections.len() / VALUES_PER_IMAGE,
        scene.train.len(),
        config.scene
    );
    let cameras: Vec<_> = scene
        .train
        .iter()
        .zip(corrections.chunks_exact(VALUES_PER_IMAGE))
        .map(|(frame, values)| {
            let mut camera = frame.camera;
            camera.camera_to_world = corrected_pose(values, camera.camera_to_world);
            (frame.image_path.clone(), camera)
        })
        .collect();
    let json = zrak::scene::camera_export::transforms_json(&cameras, scene.unit_cube);
    let text = serde_json::to_string_pretty(&json)?;
    zrak::files::write_bytes_atomically(&args.out, text.as_bytes())
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "wrote the {} corrected training cameras to {}",
        cameras.len(),
        args.out.display()
    );
    Ok(())
}

/// Refuses an output that could not be written, before any work: an
/// existing file without `force`, a missing or read-only folder.
fn check_output(out: &Path, force: bool) -> anyhow::Result<()> {
    if !force && zrak::files::exists_at_all(out) {
        anyhow::bail!(
            "{} already exists; give --force to replace it",
            out.display()
        );
    }
    let folder = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !folder.is_dir() {
        anyhow::bail!(
            "{}: cannot write there ({})",
            out.display(),
            zrak::files::describe_not_a_folder(folder)
        );
    }
    // A probe beside the output, as the atomic write will make.
    let probe = zrak::files::temporary_beside(out);
    std::fs::File::create_new(&probe)
        .map_err(|e| anyhow::anyhow!("{}: cannot write there: {e}", out.display()))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

fn check_mesh_args(args: &MeshArgs) -> anyhow::Result<()> {
    MeshFormat::of_path(&args.out).map_err(anyhow::Error::msg)?;
    anyhow::ensure!(
        (2..=MAX_RESOLUTION).contains(&args.resolution),
        "--resolution must be 2 to {MAX_RESOLUTION} grid nodes a side, got {}",
        args.resolution
    );
    if let Some(threshold) = args.threshold {
        anyhow::ensure!(
            threshold.is_finite() && threshold > 0.0,
            "--threshold must be a positive density, got {threshold}"
        );
    }
    check_output(&args.out, args.force)
}

fn export_mesh(args: MeshArgs) -> anyhow::Result<()> {
    check_mesh_args(&args)?;
    let folder = RunFolder::open(&args.run).map_err(anyhow::Error::msg)?;
    let crop = args.crop.resolve(&args.run)?;
    let (config, trainer) = restore_run(&folder, Some(EngineKind::Cpu), None)?;
    let scene = &trainer.scene;
    let region = crop.unwrap_or_else(|| CropBox::of_aabb(&scene.bounds));
    let (dims, spacing) = grid_dims(region.bounding_aabb().size(), args.resolution);
    zrak::files::check_memory(
        &format!("a {}×{}×{} grid", dims[0], dims[1], dims[2]),
        mesh_bytes(dims),
    )
    .map_err(anyhow::Error::msg)?;
    let threshold = args
        .threshold
        .unwrap_or_else(|| default_threshold(config.model, scene.unit_cube.scale));
    println!(
        "meshing {} at σ = {threshold} on a {}×{}×{} grid (cells of {:.4} world units)",
        config.model.name(),
        dims[0],
        dims[1],
        dims[2],
        spacing.max_element()
    );
    let settings = MeshSettings {
        resolution: args.resolution,
        threshold,
        region,
        min_component: args.min_component,
    };
    let started = Instant::now();
    let bar = ProgressBar::new(1000);
    let (mesh, report) = extract_mesh(trainer.model.as_ref(), &settings, &mut |share| {
        bar.set_position((share * 1000.0) as u64)
    })
    .map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    mesh.write(&args.out).map_err(anyhow::Error::msg)?;
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "wrote {}: {} vertices, {} faces{} ({seconds:.1} s)",
        args.out.display(),
        mesh.positions.len(),
        mesh.faces.len(),
        match report.components_dropped {
            0 => String::new(),
            n => format!(", {n} small pieces dropped"),
        }
    );
    if mesh.faces.is_empty() {
        note(&empty_mesh_advice(threshold, args.min_component, &report));
    }
    Ok(())
}

/// Why the mesh came out empty, and what to change.
fn empty_mesh_advice(
    threshold: f32,
    min_component: Option<MinComponent>,
    report: &zrak::mesh::extract::MeshReport,
) -> String {
    match min_component {
        Some(min) if report.components_before > 0 => {
            let (pieces, largest) = (report.components_before, report.largest_component_faces);
            format!(
                "the mesh is empty: --min-component {} removed all {pieces} piece{} of the \
                 surface at σ = {threshold}, the largest of {largest} face{}; give a \
                 --min-component of {largest} faces or fewer to keep it",
                match min {
                    MinComponent::Faces(faces) => format!("{faces}"),
                    MinComponent::Fraction(share) => format!("{}%", share * 100.0),
                },
                if pieces == 1 { "" } else { "s" },
                if largest == 1 { "" } else { "s" },
            )
        }
        _ => format!(
            "the mesh is empty: no density above {threshold} in the box; give a lower --threshold"
        ),
    }
}

fn check_points_args(args: &PointsArgs) -> anyhow::Result<()> {
    let extension = args
        .out
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    anyhow::ensure!(
        extension.as_deref() == Some("ply"),
        "{}: a point cloud is written as PLY; give a .ply file",
        args.out.display()
    );
    anyhow::ensure!(
        (1..=100_000_000).contains(&args.max_rays),
        "--max-rays must be 1 to 100000000, got {}",
        args.max_rays
    );
    anyhow::ensure!(
        (0.0..=1.0).contains(&args.min_opacity),
        "--min-opacity must be 0 to 1, got {}",
        args.min_opacity
    );
    check_output(&args.out, args.force)
}

fn export_points(args: PointsArgs) -> anyhow::Result<()> {
    check_points_args(&args)?;
    // Each ray's point takes 15 bytes in the file and 15 in memory.
    zrak::files::check_memory(
        &format!("{} points", args.max_rays),
        args.max_rays as u64 * 30,
    )
    .map_err(anyhow::Error::msg)?;
    let folder = RunFolder::open(&args.run).map_err(anyhow::Error::msg)?;
    let crop = args.crop.resolve(&args.run)?;
    let (_, mut trainer) = restore_run(&folder, Some(EngineKind::Cpu), None)?;
    trainer.model.set_crop(crop).map_err(anyhow::Error::msg)?;
    let views = trainer.scene.photographed_training_views();
    let stride = stride_for(views, args.max_rays);
    let settings = PointSettings {
        stride,
        min_opacity: args.min_opacity,
        crop,
    };
    let started = Instant::now();
    let bar = ProgressBar::new(views.len() as u64);
    let (positions, colours) =
        extract_points(trainer.model.as_ref(), views, &settings, &mut |done| {
            bar.set_position(done as u64)
        });
    bar.finish_and_clear();
    zrak::files::write_bytes_atomically(&args.out, &points_to_ply(&positions, &colours))
        .with_context(|| format!("{}: cannot write the point cloud", args.out.display()))?;
    println!(
        "wrote {}: {} points from {} views, every {stride}th pixel ({:.1} s)",
        args.out.display(),
        positions.len(),
        views.len(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[derive(clap::Parser, Debug)]
    struct Export {
        #[command(subcommand)]
        command: ExportCommand,
    }

    fn mesh_args(args: &[&str]) -> MeshArgs {
        parse_args(args).unwrap_or_else(|e| panic!("{args:?}: {e}"))
    }

    #[test]
    fn mesh_defaults() {
        let args = mesh_args(&["RUN", "--out", "scene.ply"]);
        assert_eq!(args.resolution, 256);
        assert_eq!(args.threshold, None);
        assert_eq!(args.min_component, None);
        assert!(args.crop.crop.is_none() && !args.force);
        let args = mesh_args(&[
            "RUN",
            "--out",
            "scene.obj",
            "--min-component",
            "2%",
            "--crop",
            "0,0,0,1,1,1",
        ]);
        assert_eq!(args.min_component, Some(MinComponent::Fraction(0.02)));
        assert!(matches!(args.crop.crop, Some(CropArg::Box(_))));
    }

    #[test]
    fn a_crop_box_may_start_with_a_negative_centre() {
        let args = mesh_args(&["RUN", "--out", "m.ply", "--crop", "-0.5,0,0,1,2,2"]);
        assert!(matches!(args.crop.crop, Some(CropArg::Box(_))));
    }

    #[test]
    fn bad_mesh_settings_are_refused_before_the_run_loads() {
        let dir = tempfile::tempdir().unwrap();
        let out = |name: &str| dir.path().join(name).display().to_string();
        let refusal = |args: &[&str]| check_mesh_args(&mesh_args(args)).unwrap_err().to_string();
        assert!(check_mesh_args(&mesh_args(&["RUN", "--out", &out("a.ply")])).is_ok());
        assert_eq!(
            refusal(&["RUN", "--out", &out("a.stl")]),
            format!(
                "{}: unknown mesh format `.stl`; give a .ply or .obj file",
                out("a.stl")
            )
        );
        assert_eq!(
            refusal(&["RUN", "--out", &out("a.ply"), "--resolution", "0"]),
            "--resolution must be 2 to 2048 grid nodes a side, got 0"
        );
        assert_eq!(
            refusal(&["RUN", "--out", &out("a.ply"), "--resolution", "100000"]),
            "--resolution must be 2 to 2048 grid nodes a side, got 100000"
        );
        assert_eq!(
            refusal(&["RUN", "--out", &out("a.ply"), "--threshold=-1"]),
            "--threshold must be a positive density, got -1"
        );
        // A folder that does not exist, and a file already there.
        let missing = out("no/such/a.ply");
        assert!(
            refusal(&["RUN", "--out", &missing])
                .starts_with(&format!("{missing}: cannot write there")),
            "{}",
            refusal(&["RUN", "--out", &missing])
        );
        std::fs::write(out("old.obj"), "").unwrap();
        assert!(
            refusal(&["RUN", "--out", &out("old.obj")]).contains("already exists; give --force")
        );
        assert!(check_mesh_args(&mesh_args(&["RUN", "--out", &out("old.obj"), "--force"])).is_ok());
        // Bad numbers in --crop and --min-component are parse errors.
        for args in [
            &["RUN", "--out", "a.ply", "--crop", "1,2"][..],
            &["RUN", "--out", "a.ply", "--min-component", "lots"][..],
        ] {
            assert!(parse_args::<MeshArgs>(args).is_err(), "{args:?}");
        }
    }

    #[test]
    fn bad_point_settings_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let out = |name: &str| dir.path().join(name).display().to_string();
        let refusal = |args: &[&str]| {
            check_points_args(&parse_args::<PointsArgs>(args).unwrap())
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            refusal(&["RUN", "--out", &out("p.obj")]),
            format!(
                "{}: a point cloud is written as PLY; give a .ply file",
                out("p.obj")
            )
        );
        assert_eq!(
            refusal(&["RUN", "--out", &out("p.ply"), "--max-rays", "0"]),
            "--max-rays must be 1 to 100000000, got 0"
        );
        assert_eq!(
            refusal(&["RUN", "--out", &out("p.ply"), "--min-opacity", "2"]),
            "--min-opacity must be 0 to 1, got 2"
        );
    }

    #[test]
    fn the_subcommands_parse() {
        use clap::Parser;
        let parsed = Export::try_parse_from(["export", "points", "RUN", "--out", "p.ply"]).unwrap();
        assert!(matches!(parsed.command, ExportCommand::Points(_)));
        let parsed = Export::try_parse_from(["export", "mesh", "RUN", "--out", "m.ply"]).unwrap();
        assert!(matches!(parsed.command, ExportCommand::Mesh(_)));
    }
}
