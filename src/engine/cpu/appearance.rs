//! Appearance embeddings on the `cpu` engine: each row's vector written into
//! a colour network's input, and the gradient of those columns added back
//! to the table's rows (see [`crate::field::appearance`]).

use crate::field::appearance::{Appearance, AppearanceShape};

/// What a forward pass keeps of its rows' appearance for the backward pass.
#[derive(Debug, Default)]
pub(crate) struct KeptAppearance {
    /// Each row's training image, for a pass of [`Appearance::PerSample`].
    images: Vec<u32>,
    /// Whether the rows took their own images' vectors.
    per_sample: bool,
    /// The one image every row took where they shared one (`None` with
    /// `per_sample` false: the mean).
    image: Option<u32>,
}

impl KeptAppearance {
    pub(crate) fn bytes(&self) -> usize {
        4 * self.images.capacity()
    }
}

/// Writes each row's appearance vector into columns `column..column +
/// width` of `input` (rows of `input_width`), from `table` (the field's
/// embeddings), and keeps which rows took which in `kept` where a backward
/// pass follows.
pub(crate) fn write_appearance(
    shape: &AppearanceShape,
    table: &[f32],
    appearance: Appearance<'_>,
    input: &mut [f32],
    input_width: usize,
    column: usize,
    kept: Option<&mut KeptAppearance>,
) {
    use rayon::prelude::*;
    let width = shape.width;
    let rows = input.len() / input_width;
    let columns = column..column + width;
    match shape.shared_vector(table, appearance) {
        Some(vector) => input
            .par_chunks_mut(input_width)
            .for_each(|row| row[columns.clone()].copy_from_slice(&vector)),
        None => {
            let Appearance::PerSample(images) = appearance else {
                unreachable!("only per-sample appearance has no shared vector")
            };
            assert_eq!(images.len(), rows, "an image per sample");
            input
                .par_chunks_mut(input_width)
                .zip(images.par_iter())
                .for_each(|(row, &image)| {
                    let image = image as usize;
                    assert!(image < shape.images, "image {image} of {}", shape.images);
                    row[columns.clone()].copy_from_slice(&table[image * width..][..width]);
                });
        }
    }
    if let Some(kept) = kept {
        kept.images.clear();
        kept.per_sample = false;
        kept.image = None;
        match appearance {
            Appearance::PerSample(images) => {
                kept.images.extend_from_slice(images);
                kept.per_sample = true;
            }
            Appearance::Image(image) => kept.image = Some(image),
            Appearance::None | Appearance::Mean => {}
        }
    }
}

/// Adds to `table_gradient` the gradient of the appearance columns
/// `column..column + width` of `d_input` (rows of `d_width`): each row's to
/// its image's vector, or for rows that shared one, their sum to that
/// image's (the mean's to every image's, divided by their count).
pub(crate) fn appearance_backward(
    shape: &AppearanceShape,
    kept: &KeptAppearance,
    d_input: &[f32],
    d_width: usize,
    column: usize,
    table_gradient: &mut [f32],
) {
    let width = shape.width;
    assert_eq!(
        table_gradient.len(),
        shape.param_count(),
        "the table's gradient"
    );
    let rows = d_input
        .chunks_exact(d_width)
        .map(|row| &row[column..column + width]);
    if kept.per_sample {
        assert_eq!(
            kept.images.len(),
            d_input.len() / d_width,
            "an image per row"
        );
        for (row, &image) in rows.zip(&kept.images) {
            let target = &mut table_gradient[image as usize * width..][..width];
            for (t, &g) in target.iter_mut().zip(row) {
                *t += g;
            }
        }
        return;
    }
    let mut sum = vec![0f64; width];
    for row in rows {
        for (s, &g) in sum.iter_mut().zip(row) {
            *s += g as f64;
        }
    }
    match kept.image {
        Some(image) => {
            let target = &mut table_gradient[image as usize * width..][..width];
            for (t, &s) in target.iter_mut().zip(&sum) {
                *t += s as f32;
            }
        }
        None => {
            let share: Vec<f32> = sum
                .iter()
                .map(|&s| (s / shape.images as f64) as f32)
                .collect();
            for target in table_gradient.chunks_exact_mut(width) {
                for (t, &s) in target.iter_mut().zip(&share) {
                    *t += s;
                }
            }
        }
    }
}
