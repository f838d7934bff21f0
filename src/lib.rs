//! shadowcull: bakes shadow caster culling flags for BigWorld worlds without a
//! GPU. See ARCHITECTURE.md for the code map.

pub mod bake;
pub mod cache;
pub mod classify;
pub mod diff;
pub mod digest;
pub mod error;
pub mod explain;
pub mod files;
pub mod formats;
pub mod gen;
pub mod inspect;
pub mod light;
pub mod progress;
#[cfg(feature = "raster")]
pub mod raster;
pub mod render;
pub mod report_html;
pub mod rng;
pub mod scene;
pub mod sweep;
pub mod trace;

pub use error::{Error, Result};
