//! The integration tests, one binary (see ARCHITECTURE.md, "Testing").

mod bad_input;
mod bake_rules;
mod bake_world;
mod cache;
mod cli;
mod diff;
mod explain;
mod fuzz;
mod generated;
mod ground;
mod hardening;
mod html;
mod memory;
mod micro;
mod nomiss;
mod occlusion;
mod packed_real;
mod packed_world;
mod pipeline;
mod primitives_real;
#[cfg(feature = "raster")]
mod raster;
mod real_scene;
mod render;
mod robustness;
mod shadow_write_real;
mod shards;
mod speedtrees;
mod support;
mod sweep;
mod terrain_real;
mod tiles;
mod visual_real;
mod xml_real;
