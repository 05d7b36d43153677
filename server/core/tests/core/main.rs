//! esrp-core's integration tests: one binary, one module per concern.

mod collision;
mod fixtures;
mod properties;
mod rules;
mod spec;
mod validation;
