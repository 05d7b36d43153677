//! esrp-dataset's integration tests: one binary, one module per concern.

// The command line is built only with the `cli` feature (a default one).
#[cfg(feature = "cli")]
mod cli;
#[cfg(feature = "cli")]
mod cli_input;
mod generation;
mod versions;
