//! The viewer's mesh and point-cloud exports, a unit at a time: a slab of
//! the density grid (then marching cubes, colours and the file), or a
//! training view's rays. The same functions as `zrak export mesh|points`.

use std::path::PathBuf;
use std::sync::Arc;

use glam::Vec3;

use crate::field::ModelKind;
use crate::mesh::extract::{
    DensitySampler, MAX_RESOLUTION, MeshSettings, default_threshold, grid_dims, mesh_bytes,
};
use crate::mesh::points::{PointSettings, points_of_view, stride_for};
use crate::mesh::{MeshFormat, points_to_ply};
use crate::model::RadianceModel;
use crate::scene::Scene;
use crate::scene::crop::CropBox;
use crate::session::protocol::{MeshExport, PointsExport};

/// A mesh being extracted.
pub(super) struct MeshJob {
    sampler: DensitySampler,
    out: PathBuf,
}

impl MeshJob {
    /// Checks the order, the output file (an existing one only with
    /// `replace_existing`) and the memory the grid takes.
    pub(super) fn start(
        scene: &Scene,
        order: MeshExport,
        model: ModelKind,
        crop: Option<CropBox>,
    ) -> Result<Self, String> {
        MeshFormat::of_path(&order.out)?;
        if !(2..=MAX_RESOLUTION).contains(&order.resolution) {
            return Err(format!(
                "the resolution must be 2 to {MAX_RESOLUTION} grid nodes a side, got {}",
                order.resolution
            ));
        }
        crate::files::check_new_file(&order.out, order.replace_existing)?;
        let region = crop.unwrap_or_else(|| CropBox::of_aabb(&scene.bounds));
        let (dims, _) = grid_dims(region.bounding_aabb().size(), order.resolution);
        crate::files::check_memory(
            &format!("a {}×{}×{} grid", dims[0], dims[1], dims[2]),
            mesh_bytes(dims),
        )?;
        let settings = MeshSettings {
            resolution: order.resolution,
            threshold: order
                .threshold
                .unwrap_or_else(|| default_threshold(model, scene.unit_cube.scale)),
            region,
            min_component: order.min_component,
        };
        Ok(Self {
            sampler: DensitySampler::new(&settings)?,
            out: order.out,
        })
    }

    /// Slabs sampled, and slabs plus the surface in all.
    pub(super) fn progress(&self) -> (usize, usize) {
        (self.sampler.slabs_done(), self.sampler.slabs() + 1)
    }

    pub(super) fn step(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        self.sampler.sample_slab(model)
    }

    /// Marching cubes, the vertices' colours, and the file (written whole
    /// or not at all).
    pub(super) fn finish(self, model: &dyn RadianceModel) -> Result<Vec<PathBuf>, String> {
        let (mesh, _) = self.sampler.finish(model)?;
        mesh.write(&self.out)?;
        Ok(vec![self.out])
    }
}

/// A point cloud being gathered, a training view at a time.
pub(super) struct PointsJob {
    /// The scene whose photographed training views cast the rays.
    scene: Arc<Scene>,
    views: usize,
    settings: PointSettings,
    done: usize,
    positions: Vec<Vec3>,
    colours: Vec<[u8; 3]>,
    out: PathBuf,
}

impl PointsJob {
    pub(super) fn start(
        scene: Arc<Scene>,
        order: PointsExport,
        crop: Option<CropBox>,
    ) -> Result<Self, String> {
        let is_ply = order
            .out
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
        if !is_ply {
            return Err(format!(
                "{}: a point cloud is written as PLY; give a .ply file",
                order.out.display()
            ));
        }
        if !(1..=100_000_000).contains(&order.max_rays) {
            return Err(format!(
                "the rays must be 1 to 100000000, got {}",
                order.max_rays
            ));
        }
        if !(0.0..=1.0).contains(&order.min_opacity) {
            return Err(format!(
                "the least opacity must be 0 to 1, got {}",
                order.min_opacity
            ));
        }
        crate::files::check_new_file(&order.out, order.replace_existing)?;
        // Each point takes 15 bytes in the file and 15 in memory.
        crate::files::check_memory(
            &format!("{} points", order.max_rays),
            order.max_rays as u64 * 30,
        )?;
        let views = scene.photographed_training_views();
        if views.is_empty() {
            return Err("the scene has no photographed training views to cast rays from".into());
        }
        Ok(Self {
            settings: PointSettings {
                stride: stride_for(views, order.max_rays),
                min_opacity: order.min_opacity,
                crop,
            },
            views: views.len(),
            scene,
            done: 0,
            positions: Vec::new(),
            colours: Vec::new(),
            out: order.out,
        })
    }

    pub(super) fn progress(&self) -> (usize, usize) {
        (self.done, self.views)
    }

    pub(super) fn step(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        if let Some(view) = self.scene.photographed_training_views().get(self.done) {
            points_of_view(
                model,
                view,
                &self.settings,
                &mut self.positions,
                &mut self.colours,
            );
            self.done += 1;
        }
        Ok(self.done < self.views)
    }

    pub(super) fn finish(self) -> Result<Vec<PathBuf>, String> {
        crate::files::write_bytes_atomically(
            &self.out,
            &points_to_ply(&self.positions, &self.colours),
        )
        .map_err(|e| format!("{}: cannot write the point cloud: {e}", self.out.display()))?;
        Ok(vec![self.out])
    }
}
