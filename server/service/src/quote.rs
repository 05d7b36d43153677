//! Client-given text in error messages, bounded: error messages travel in response metadata,
//! which clients cap (16 KiB in grpcio), so no message may echo an unbounded value. A leaf: it
//! uses no other module of the crate.

/// The most characters of a client-given value that an error message quotes.
pub const MAX_QUOTED_CHARS: usize = 64;

/// The most characters of a client-derived message (a scene's parse error) that an error
/// message carries.
pub const MAX_QUOTED_MESSAGE: usize = 1024;

/// A client-given value as an error message shows it: whole if it has at most
/// [`MAX_QUOTED_CHARS`] characters, else its first ones, an ellipsis and its length. Error
/// messages travel in response metadata, which clients cap (16 KiB in grpcio), so no message
/// may echo an unbounded value.
#[derive(Clone, Copy, Debug)]
pub struct Bounded<'a> {
    text: &'a str,
    quote: bool,
}

/// `text` quoted and escaped like `{:?}`: `"abc"`, or `"aaaa…" (20000 characters)`.
pub fn quoted(text: &str) -> Bounded<'_> {
    Bounded { text, quote: true }
}

/// `text` as it is: `abc`, or `aaaa… (20000 characters)`.
pub fn bounded(text: &str) -> Bounded<'_> {
    Bounded { text, quote: false }
}

/// The first `max` characters of `text` (char-boundary safe) and whether it was longer.
fn head(text: &str, max: usize) -> (&str, bool) {
    match text.char_indices().nth(max) {
        Some((end, _)) => (&text[..end], true),
        None => (text, false),
    }
}

impl std::fmt::Display for Bounded<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (head, cut) = head(self.text, MAX_QUOTED_CHARS);
        match (cut, self.quote) {
            (false, true) => write!(f, "{head:?}"),
            (false, false) => f.write_str(head),
            (true, true) => write!(f, "{:?} ({} characters)", format!("{head}…"), self.text.chars().count()),
            (true, false) => write!(f, "{head}… ({} characters)", self.text.chars().count()),
        }
    }
}

/// `message` cut to its first `max` characters and an ellipsis if longer.
pub fn bound_message(message: &str, max: usize) -> String {
    match head(message, max) {
        (head, true) => format!("{head}…"),
        (head, false) => head.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_values_in_messages_are_bounded() {
        assert_eq!(quoted("e1").to_string(), "\"e1\"");
        assert_eq!(bounded("e1").to_string(), "e1");
        let long = "é".repeat(20_000);
        let shown = quoted(&long).to_string();
        assert!(shown.starts_with(&format!("\"{}…\"", "é".repeat(MAX_QUOTED_CHARS))), "{shown}");
        assert!(shown.ends_with(" (20000 characters)"), "{shown}");
        assert_eq!(bounded(&long).to_string(), format!("{}… (20000 characters)", "é".repeat(MAX_QUOTED_CHARS)));
        let exact = "a".repeat(MAX_QUOTED_CHARS);
        assert_eq!(bounded(&exact).to_string(), exact);
        assert_eq!(bound_message(&long, 3), "ééé…");
        assert_eq!(bound_message("abc", 3), "abc");
    }
}
