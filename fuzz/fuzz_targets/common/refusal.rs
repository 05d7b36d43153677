//! What every request target checks of a refusal (shared with `#[path]`: each target is its own
//! binary crate).

use tonic::Code;

/// The longest message an error about client input may have (as the property tests of
/// `server/service/tests/server/conversions.rs`).
pub const MAX_MESSAGE: usize = 1200;

/// A refusal of client input: INVALID_ARGUMENT or NOT_FOUND, with a bounded message.
pub fn refused(code: Code, message: &str) {
    assert!(matches!(code, Code::InvalidArgument | Code::NotFound), "{code:?}: {message}");
    assert!(message.len() <= MAX_MESSAGE, "a {}-byte message", message.len());
}
