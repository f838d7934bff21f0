//! The integration tests, one binary (see ARCHITECTURE.md, "Testing").

mod bad_input;
mod cli;
mod generated;
mod packed_real;
mod primitives_real;
mod real_scene;
mod shadow_write_real;
mod support;
mod terrain_real;
mod visual_real;
mod xml_real;
