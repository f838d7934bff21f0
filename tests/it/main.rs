//! The integration tests, one binary (see ARCHITECTURE.md, "Testing").

mod support;
mod terrain_real;
