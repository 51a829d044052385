//! Rendering through the occupancy grid: rays marched and composited in
//! rounds, each stopping once its transmittance is spent. Both engines
//! render this way, with their own field evaluating each round.

use super::*;

/// A round of samples handed to the field while rendering through the grid.
pub struct GridSamples<'a> {
    /// n × 3, unit-cube coordinates.
    pub positions: &'a [f32],
    /// n × 3, each sample's ray's unit world direction.
    pub directions: &'a [f32],
    /// n, distance from the ray's origin in world units.
    pub t: &'a [f32],
    /// n, the index of each sample's ray among the rays rendered.
    pub rays: &'a [u32],
    /// n, each sample's step in world units.
    pub dt: &'a [f32],
}

/// How [`march_and_composite`] renders rays through the grid.
#[derive(Clone, Copy)]
pub struct GridRendering<'a> {
    /// From the scene's world to the grid's unit cube.
    pub mapping: &'a UnitCubeMapping,
    /// The step, and where a ray stops: `min_transmittance`, `max_steps`.
    pub config: &'a MarchConfig,
    /// Seen through what transmittance a ray has left.
    pub background: [f32; 3],
    /// About how many samples the field evaluates in a round.
    pub chunk_samples: usize,
}

/// Where [`march_and_composite`] writes, per ray of R.
pub struct CompositedRays<'a> {
    /// R × 3.
    pub colour: &'a mut [f32],
    /// R, expected depth in world units.
    pub depth: &'a mut [f32],
    /// R.
    pub opacity: &'a mut [f32],
}

/// Renders R rays through a field with early termination: densities and
/// colours are evaluated in rounds of about `rendering.chunk_samples`
/// samples; each ray stops once its transmittance falls below
/// `config.min_transmittance`, after `config.max_steps` samples, or when
/// it leaves the box. Compositing as in [`crate::engine::cpu::composite::composite`]
/// (wᵢ = Tᵢ(1 − e^(−σᵢδᵢ)), expected depth Σwᵢtᵢ, background weighted by the
/// final transmittance), so up to the 1e-4 cut-off the result equals
/// marching everything and compositing it.
///
/// `field(samples, density n, rgb n×3)` fills the last two for a round of
/// n [`GridSamples`].
pub fn march_and_composite<F>(
    grid: &OccupancyGrid,
    rendering: GridRendering,
    origins: &[f32],
    directions: &[f32],
    mut field: F,
    out: CompositedRays,
) where
    F: FnMut(&GridSamples, &mut [f32], &mut [f32]),
{
    let GridRendering {
        mapping,
        config,
        background,
        chunk_samples,
    } = rendering;
    let CompositedRays {
        colour,
        depth,
        opacity,
    } = out;
    let ray_count = origins.len() / 3;
    assert_eq!(directions.len(), 3 * ray_count);
    assert!(
        colour.len() == 3 * ray_count && depth.len() == ray_count && opacity.len() == ray_count
    );
    let marcher = Marcher::new(grid, config, mapping);

    #[derive(Clone, Copy)]
    struct State {
        ray: Option<RayMarch>,
        k: u32,
        emitted: u32,
        optical_depth: f32,
        colour: [f32; 3],
        depth: f32,
    }
    let mut states: Vec<State> = (0..ray_count)
        .into_par_iter()
        .map(|r| State {
            ray: marcher.prepare(
                Vec3::from_slice(&origins[3 * r..3 * r + 3]),
                Vec3::from_slice(&directions[3 * r..3 * r + 3]),
                0.0,
            ),
            k: 0,
            emitted: 0,
            optical_depth: 0.0,
            colour: [0.0; 3],
            depth: 0.0,
        })
        .collect();
    let mut active: Vec<u32> = (0..ray_count as u32)
        .filter(|&r| states[r as usize].ray.is_some())
        .collect();
    let stop_depth = -config.min_transmittance.ln();
    let chunk = chunk_samples.max(1);

    let mut counts: Vec<u32> = Vec::new();
    let mut next: Vec<u32> = Vec::new();
    let mut lattice: Vec<u32> = Vec::new();
    let mut positions: Vec<f32> = Vec::new();
    let mut sample_directions: Vec<f32> = Vec::new();
    let mut sample_t: Vec<f32> = Vec::new();
    let mut sample_rays: Vec<u32> = Vec::new();
    let mut sample_dt: Vec<f32> = Vec::new();
    let mut sigma: Vec<f32> = Vec::new();
    let mut rgb: Vec<f32> = Vec::new();
    let mut finished: Vec<bool> = Vec::new();
    while !active.is_empty() {
        // Few samples per ray while many rays are active (most stop early on
        // opaque surfaces), more once few are left; 4 to 64 per round.
        let per_ray = (chunk / active.len()).clamp(4, 64);
        let group = (chunk / per_ray).max(1);
        for rays in active.chunks(group) {
            counts.resize(rays.len(), 0);
            next.resize(rays.len(), 0);
            lattice.resize(rays.len() * per_ray, 0);
            finished.resize(rays.len(), false);
            // March each ray's next few samples into its own slots.
            counts
                .par_iter_mut()
                .zip(next.par_iter_mut())
                .zip(lattice.par_chunks_mut(per_ray))
                .zip(finished.par_iter_mut())
                .zip(rays.par_iter())
                .for_each(|((((count, next), slots), done), &r)| {
                    let state = &states[r as usize];
                    let ray = state.ray.as_ref().expect("active rays hit the box");
                    let limit = (per_ray as u32).min(config.max_steps - state.emitted);
                    let mut k = state.k;
                    let mut n = 0;
                    *done = marcher.walk(ray, &mut k, limit, |k| {
                        slots[n] = k;
                        n += 1;
                    });
                    *next = k;
                    *count = n as u32;
                });
            let total: usize = counts.iter().map(|&c| c as usize).sum();
            positions.clear();
            sample_directions.clear();
            sample_t.clear();
            sample_rays.clear();
            sample_dt.clear();
            for (i, &r) in rays.iter().enumerate() {
                let ray = states[r as usize].ray.as_ref().expect("active");
                for &k in &lattice[i * per_ray..i * per_ray + counts[i] as usize] {
                    positions.extend_from_slice(&ray.position(k).to_array());
                    sample_directions.extend_from_slice(&ray.direction.to_array());
                    sample_t.push(marcher.world_t(ray, k));
                    sample_rays.push(r);
                    sample_dt.push(marcher.world_dt(ray, k));
                }
            }
            sigma.resize(total, 0.0);
            rgb.resize(3 * total, 0.0);
            if total > 0 {
                let samples = GridSamples {
                    positions: &positions,
                    directions: &sample_directions,
                    t: &sample_t,
                    rays: &sample_rays,
                    dt: &sample_dt,
                };
                field(&samples, &mut sigma, &mut rgb);
            }
            // Composite, in order along each ray, and advance its state.
            let mut offset = 0;
            for (i, &r) in rays.iter().enumerate() {
                let state = &mut states[r as usize];
                let ray = state.ray.expect("active");
                let n = counts[i] as usize;
                for j in 0..n {
                    if state.optical_depth > stop_depth {
                        break;
                    }
                    let k = lattice[i * per_ray + j];
                    let tau = (sigma[offset + j] * marcher.world_dt(&ray, k)).max(0.0);
                    let weight = (-state.optical_depth).exp() * -(-tau).exp_m1();
                    for c in 0..3 {
                        state.colour[c] += weight * rgb[3 * (offset + j) + c];
                    }
                    state.depth += weight * marcher.world_t(&ray, k);
                    state.optical_depth += tau;
                }
                offset += n;
                state.emitted += n as u32;
                state.k = next[i];
                if finished[i]
                    || state.emitted >= config.max_steps
                    || state.optical_depth > stop_depth
                {
                    state.ray = None;
                }
            }
        }
        active.retain(|&r| states[r as usize].ray.is_some());
    }

    for (r, state) in states.iter().enumerate() {
        let transmittance = (-state.optical_depth).exp();
        for c in 0..3 {
            colour[3 * r + c] = state.colour[c] + transmittance * background[c];
        }
        depth[r] = state.depth;
        opacity[r] = 1.0 - transmittance;
    }
}

/// The marching jitter seed of a step (both engines, so they march the
/// same samples).
pub fn mix_seed(seed: u64, step: u32) -> u32 {
    let mixed = (seed ^ 0x6a69_7474).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ step as u64;
    (mixed ^ (mixed >> 32)) as u32
}

/// Renders rays with early termination through the occupancy grid, with
/// `field` giving σ and colour for each round of samples (see
/// [`march_and_composite`]).
#[allow(clippy::too_many_arguments)]
pub fn render_through_grid(
    grid: &OccupancyGrid,
    mapping: &UnitCubeMapping,
    origins: &[Vec3],
    directions: &[Vec3],
    background: [f32; 3],
    config: &MarchConfig,
    chunk_samples: usize,
    field: impl FnMut(&GridSamples, &mut [f32], &mut [f32]),
    out: &mut [RenderedPixel],
) {
    let n = origins.len();
    let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
    let (origins, directions) = (flat(origins), flat(directions));
    let mut colour = vec![0f32; 3 * n];
    let mut depth = vec![0f32; n];
    let mut opacity = vec![0f32; n];
    march_and_composite(
        grid,
        GridRendering {
            mapping,
            config,
            background,
            chunk_samples,
        },
        &origins,
        &directions,
        field,
        CompositedRays {
            colour: &mut colour,
            depth: &mut depth,
            opacity: &mut opacity,
        },
    );
    for (i, pixel) in out.iter_mut().enumerate().take(n) {
        *pixel = RenderedPixel {
            rgb: [colour[3 * i], colour[3 * i + 1], colour[3 * i + 2]],
            opacity: opacity[i],
            depth: depth[i],
        };
    }
}
