//! Every integration test of zrak, one module per subject, in one test
//! crate: one binary links zrak, wgpu and egui once, where one binary per
//! file linked them 33 times over (issue 28).
//!
//! One process now runs them all, two at a time on two cores, so what a
//! binary of its own used to keep apart is kept apart here: each test holds
//! [`common::shared`] or, where it measures how the machine shares its
//! time, [`common::alone`] (see there).

mod common;

mod adam_gpu;
mod appearance;
mod appearance_gpu;
mod captures;
mod cli;
mod cli_camera_path;
mod cli_render_bounds;
mod composite_gpu;
mod demo_scene;
mod dense_gpu;
mod frequency_gpu;
mod fuzz_parsers;
mod gpu_context;
mod hard_cases;
mod hash_grid_gpu;
mod layering;
mod llff;
mod locks;
mod march_gpu;
mod masks;
mod mesh_export;
mod nerf_cpu;
mod nerf_field_gpu;
mod nerf_gpu;
mod nerf_learning;
mod ngp_cpu;
mod ngp_driver_gate;
mod ngp_field_gpu;
mod ngp_gpu;
mod ngp_gpu_driver_gate;
mod ngp_learning;
mod photographs;
mod proposal_cpu;
mod proposal_gpu;
mod proposal_nerf_cpu;
mod refine_cameras;
mod render_texture_gpu;
mod sampling_gpu;
mod scene_bounds;
mod scene_loading;
mod scene_space;
mod sh_gpu;
mod split_bindings_gpu;
mod viewer_exports;
mod viewer_gpu;
mod viewer_ui;
mod viewer_window;
mod viewer_worker;
