//! Per-image appearance embeddings (NeRF in the Wild, Martin-Brualla et al.
//! 2021, section 4.1): a learned vector per training image, appended to the
//! input of a field's colour network only, so an image's exposure and
//! white balance change the colours the field gives it, never its density.
//! Engine-neutral: the table's shape and where it sits in a field's
//! parameters, its initial values, and which vector each sample takes.

use crate::rng::Pcg32;

/// Values per image's vector (nerfstudio's nerfacto, `nerfacto.py`:
/// `NerfactoModelConfig.appearance_embed_dim` 32).
pub const EMBEDDING_WIDTH: usize = 32;

/// NeRF in the Wild's evaluation of a held-out view (section 6): its
/// appearance vector is optimised on the view's left half with the field
/// held still, and its right half is scored. Steps of Adam from the
/// training vectors' mean, rays drawn from the left half each step, and the
/// rate: zrak's choice (the paper gives none), enough for the vector to
/// move a unit (its N(0, 1) start's spread) in a few dozen steps.
pub const FIT_STEPS: u32 = 100;
pub const FIT_RAYS: usize = 2048;
pub const FIT_LEARNING_RATE: f32 = 0.05;

/// A field's table of appearance embeddings: `images` rows of `width`
/// values, after the field's other parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AppearanceShape {
    /// Training images, one row each.
    pub images: usize,
    /// Values per row.
    pub width: usize,
}

impl AppearanceShape {
    /// A table of [`EMBEDDING_WIDTH`] values for each of `images` training
    /// images.
    pub fn for_images(images: usize) -> Self {
        assert!(images > 0, "appearance embeddings need training images");
        Self {
            images,
            width: EMBEDDING_WIDTH,
        }
    }

    pub fn param_count(&self) -> usize {
        self.images * self.width
    }

    /// Initial values: each N(0, 1), as nerfstudio's `Embedding`
    /// (`field_components/embedding.py`), which is a `torch.nn.Embedding`
    /// at PyTorch's default initialisation.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 0x6170_7065_6172);
        let mut params = Vec::with_capacity(self.param_count());
        while params.len() < self.param_count() {
            // Box–Muller: two independent normals from two uniforms.
            let u1 = 1.0 - rng.next_f32(); // (0, 1]: the logarithm stays finite
            let u2 = rng.next_f32();
            let radius = (-2.0 * u1.ln()).sqrt();
            let angle = std::f32::consts::TAU * u2;
            params.push(radius * angle.cos());
            params.push(radius * angle.sin());
        }
        params.truncate(self.param_count());
        params
    }

    /// The mean of the table's rows: what a view that is no training image
    /// is rendered with (nerfacto's `use_average_appearance_embedding`).
    pub fn mean(&self, table: &[f32]) -> Vec<f32> {
        assert_eq!(table.len(), self.param_count(), "the table's size");
        let mut mean = vec![0f64; self.width];
        for row in table.chunks_exact(self.width) {
            for (m, &v) in mean.iter_mut().zip(row) {
                *m += v as f64;
            }
        }
        mean.iter()
            .map(|&m| (m / self.images as f64) as f32)
            .collect()
    }

    /// The vector `appearance` gives every sample where it gives all the
    /// same one (`None` for [`Appearance::PerSample`]): the mean for
    /// [`Appearance::None`] and [`Appearance::Mean`].
    pub fn shared_vector(&self, table: &[f32], appearance: Appearance<'_>) -> Option<Vec<f32>> {
        match appearance {
            Appearance::PerSample(_) => None,
            Appearance::None | Appearance::Mean => Some(self.mean(table)),
            Appearance::Image(image) => {
                let image = image as usize;
                assert!(
                    image < self.images,
                    "image {image} of {} with embeddings",
                    self.images
                );
                Some(table[image * self.width..][..self.width].to_vec())
            }
        }
    }
}

/// Which appearance vector each sample of a field's pass takes. Fields
/// without a table ignore it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Appearance<'a> {
    /// None asked for: a field with a table takes the mean, as for
    /// [`Appearance::Mean`] (density-only fields, tests of a field alone).
    None,
    /// Each sample's training image, the image of its ray (training).
    PerSample(&'a [u32]),
    /// The mean of the training images' vectors (renders, held-out views).
    Mean,
    /// One training image's vector for every sample (the viewer's choice).
    Image(u32),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_initial_table_is_standard_normal_and_reproducible() {
        let shape = AppearanceShape::for_images(200);
        let table = shape.init_params(3);
        assert_eq!(table.len(), 200 * EMBEDDING_WIDTH);
        assert_eq!(table, shape.init_params(3));
        assert_ne!(table, shape.init_params(4));
        let n = table.len() as f64;
        let mean = table.iter().map(|&v| v as f64).sum::<f64>() / n;
        let variance = table
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        // 6400 draws: the mean's standard error is 1/80, the variance's
        // about √(2/6400) ≈ 0.018; 4 of each.
        assert!(mean.abs() < 0.05, "mean {mean}");
        assert!((variance - 1.0).abs() < 0.07, "variance {variance}");
    }

    #[test]
    fn the_mean_and_a_chosen_image_take_their_rows() {
        let shape = AppearanceShape {
            images: 2,
            width: 3,
        };
        let table = [1.0, 2.0, 3.0, 3.0, 4.0, 7.0];
        assert_eq!(shape.mean(&table), vec![2.0, 3.0, 5.0]);
        assert_eq!(
            shape.shared_vector(&table, Appearance::Image(1)),
            Some(vec![3.0, 4.0, 7.0])
        );
        assert_eq!(
            shape.shared_vector(&table, Appearance::None),
            Some(vec![2.0, 3.0, 5.0])
        );
        assert_eq!(
            shape.shared_vector(&table, Appearance::PerSample(&[0])),
            None
        );
    }
}
