//! Integration tests of esrp-render on a real adapter (lavapipe in CI): golden images,
//! geometry of both cameras, depth, batching, errors and image helpers.
//!
//! There is no silent skip: without an adapter every test fails and says how to install one.

mod batch;
mod common;
mod compute;
mod errors;
mod geometry;
mod goldens;
mod images;
