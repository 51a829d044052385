//! `zrak convert`: a COLMAP model or an LLFF capture written as a
//! transforms.json.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;

#[derive(Args, Debug)]
pub struct ConvertArgs {
    /// A folder with sparse/0/cameras.bin and images.bin (or .txt) and
    /// images/, or an LLFF folder (poses_bounds.npy and images/).
    colmap: PathBuf,
    /// The transforms.json to write (an existing file is kept unless
    /// --force).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out file (never one of the model's own).
    #[arg(long)]
    force: bool,
}

pub fn convert(args: ConvertArgs) -> anyhow::Result<()> {
    let ConvertArgs { colmap, out, force } = args;
    check_not_colmap_input(&colmap, &out)?;
    if out.is_dir() {
        bail!(
            "{}: is a folder; give the path of the file to write, e.g. {}",
            out.display(),
            out.join("transforms.json").display()
        );
    }
    if zrak::files::exists_at_all(&out) && !force {
        bail!(
            "{} already exists; give --force to replace it, or another --out",
            out.display()
        );
    }
    if zrak::scene::llff::is_llff_folder(&colmap) {
        return convert_llff(&colmap, &out);
    }
    let converted = zrak::scene::colmap::convert(&colmap)?;
    let out_folder = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    // Image paths relative to the output's folder need both in the same
    // form; an absolute path is written otherwise.
    let absolute = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut absolute_images = converted.clone();
    for image in &mut absolute_images.images {
        image.image_path = absolute(&image.image_path);
    }
    let json = zrak::scene::colmap::transforms_json(&absolute_images, &absolute(out_folder));
    let text = serde_json::to_string_pretty(&json)?;
    zrak::files::write_bytes_atomically(&out, text.as_bytes())
        .with_context(|| format!("{}: cannot write", out.display()))?;
    println!(
        "wrote {} ({} frames, centre [{:.4}, {:.4}, {:.4}] and scale {:.5} applied, aabb_scale {})",
        out.display(),
        converted.images.len(),
        converted.centre.x,
        converted.centre.y,
        converted.centre.z,
        converted.scale,
        converted.unit_cube.aabb_scale
    );
    Ok(())
}

/// Writes the LLFF capture at `llff` as the transforms.json `out`: its
/// poses as zrak loads them (axes, rescale and recentring applied).
fn convert_llff(llff: &Path, out: &Path) -> anyhow::Result<()> {
    use zrak::scene::llff;
    let converted = llff::convert(llff)?;
    let out_folder = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let absolute = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut absolute_images = converted.clone();
    for (path, _) in &mut absolute_images.images {
        *path = absolute(path);
    }
    let json = llff::transforms_json(&absolute_images, &absolute(out_folder));
    let text = serde_json::to_string_pretty(&json)?;
    zrak::files::write_bytes_atomically(out, text.as_bytes())
        .with_context(|| format!("{}: cannot write", out.display()))?;
    println!(
        "wrote {} ({} frames of an LLFF capture, scale {:.5} and its average pose applied)",
        out.display(),
        converted.images.len(),
        converted.normalisation.scale,
    );
    Ok(())
}

/// `path` as it will be once written: its canonical form when it exists
/// (through any link), else its folder's canonical form and its name.
fn canonical_destination(path: &Path) -> PathBuf {
    if let Ok(canonical) = std::fs::canonicalize(path) {
        return canonical;
    }
    let parent = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    match (std::fs::canonicalize(parent), path.file_name()) {
        (Ok(folder), Some(name)) => folder.join(name),
        _ => path.to_path_buf(),
    }
}

/// Refuses an output file that is one of the COLMAP model's own files or
/// photographs: `convert` must never destroy what it reads.
fn check_not_colmap_input(colmap: &Path, out: &Path) -> anyhow::Result<()> {
    let destination = canonical_destination(out);
    if let Some(model) = zrak::scene::colmap::find_model_folder(colmap) {
        let model = std::fs::canonicalize(&model).unwrap_or(model);
        let is_model_file = destination.parent() == Some(model.as_path())
            && destination.file_name().is_some_and(|name| {
                ["cameras", "images", "points3D"].iter().any(|stem| {
                    ["bin", "txt"]
                        .iter()
                        .any(|ext| name.to_string_lossy() == format!("{stem}.{ext}"))
                })
            });
        if is_model_file {
            bail!(
                "{}: that is the COLMAP model's own {} (convert reads it); give --out \
                 another path, e.g. {}",
                out.display(),
                destination
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy(),
                colmap.join("transforms.json").display()
            );
        }
    }
    let poses = colmap.join(zrak::scene::llff::POSES_FILE);
    if zrak::files::exists_at_all(&poses)
        && std::fs::canonicalize(&poses).is_ok_and(|poses| poses == destination)
    {
        bail!(
            "{}: that is the LLFF capture's own {} (convert reads it); give --out another \
             path, e.g. {}",
            out.display(),
            zrak::scene::llff::POSES_FILE,
            colmap.join("transforms.json").display()
        );
    }
    let images = std::fs::canonicalize(colmap.join("images")).ok();
    if let Some(images) = images
        && destination.starts_with(&images)
    {
        bail!(
            "{}: that is inside the model's photographs folder {}; give --out another path",
            out.display(),
            images.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[test]
    fn convert_needs_a_model_and_an_out_file() {
        let args: ConvertArgs = parse_args(&["colmap", "--out", "t.json", "--force"]).unwrap();
        assert_eq!(args.colmap, PathBuf::from("colmap"));
        assert_eq!(args.out, PathBuf::from("t.json"));
        assert!(args.force);
        let error = parse_args::<ConvertArgs>(&["colmap"]).unwrap_err();
        assert_eq!(
            error.kind(),
            clap::error::ErrorKind::MissingRequiredArgument
        );
        assert!(error.to_string().contains("--out <OUT>"), "{error}");
    }

    #[test]
    fn a_destination_is_named_through_links_and_dots() {
        let dir = tempfile::tempdir().unwrap();
        let root = std::fs::canonicalize(dir.path()).unwrap();
        std::fs::create_dir(root.join("a")).unwrap();
        // Not there yet: its folder's canonical form and its name.
        assert_eq!(
            canonical_destination(&root.join("a/../a/new.json")),
            root.join("a/new.json")
        );
        // There, through a link: the file it points to.
        std::fs::write(root.join("a/real.json"), "{}").unwrap();
        std::os::unix::fs::symlink(root.join("a/real.json"), root.join("link.json")).unwrap();
        assert_eq!(
            canonical_destination(&root.join("link.json")),
            root.join("a/real.json")
        );
    }

    #[test]
    fn convert_never_writes_over_the_model_or_its_photographs() {
        let dir = tempfile::tempdir().unwrap();
        let colmap = dir.path();
        std::fs::create_dir_all(colmap.join("sparse/0")).unwrap();
        std::fs::create_dir_all(colmap.join("images")).unwrap();
        for file in ["cameras.txt", "images.txt", "points3D.txt"] {
            std::fs::write(colmap.join("sparse/0").join(file), "").unwrap();
        }
        let error = check_not_colmap_input(colmap, &colmap.join("sparse/0/images.txt"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("that is the COLMAP model's own images.txt (convert reads it)"),
            "{error}"
        );
        let error = check_not_colmap_input(colmap, &colmap.join("images/t.json"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("that is inside the model's photographs folder"),
            "{error}"
        );
        std::fs::write(colmap.join("poses_bounds.npy"), "").unwrap();
        let error = check_not_colmap_input(colmap, &colmap.join("poses_bounds.npy"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("that is the LLFF capture's own poses_bounds.npy"),
            "{error}"
        );
        // Beside the model is where the README writes it.
        assert!(check_not_colmap_input(colmap, &colmap.join("transforms.json")).is_ok());
        assert!(check_not_colmap_input(colmap, &colmap.join("sparse/0/t.json")).is_ok());
    }
}
