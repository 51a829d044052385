//! What both engines hold on the host and neither owns: the batch sizer
//! (rays per batch from the samples per ray the steps report), the
//! occupancy grid (its cells, bitfield and update rule; the gpu engine
//! mirrors it on the device and reads it back), Adam's state and its
//! reference update (the gpu engine's kernel keeps the same moments) and a
//! model's checkpoint state, so checkpoints move between engines; the
//! inputs of compositing (a batch's samples and rays, the distortion
//! weights), the stratified sampler's step, and the march through the
//! occupancy grid (the lattice, the walk, the seeds, the samples it yields
//! and the render loop) that the cpu engine's batch march and the gpu
//! engine's kernels both follow; the single-frustum Gaussians of Mip-NeRF;
//! and the drivers' shared helpers (model identity, ray bounds, chunk
//! seeds, the inputs of samples rendered through the grid). The gpu engine
//! takes these from here, not from the cpu engine.

pub mod adam;
pub mod batch_sizer;
pub mod camera_refinement;
pub mod composite;
pub mod driver;
pub mod frustum;
pub mod march;
pub mod occupancy;
pub mod sampling;
pub mod state;
