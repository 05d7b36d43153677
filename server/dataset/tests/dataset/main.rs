//! esrp-dataset's integration tests: one binary, one module per concern.

mod cli;
mod generation;
