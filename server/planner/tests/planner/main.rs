//! esrp-planner's integration tests: one binary, one module per concern.

mod extremes;
mod fixtures;
mod properties;
mod states;
mod v2;
