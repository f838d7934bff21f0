//! The integration tests, one binary (see ARCHITECTURE.md, "Testing").

mod primitives_real;
mod support;
mod terrain_real;
