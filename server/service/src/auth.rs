//! Who is calling. The tokens a server knows (`--token`, or `--tokens FILE` with a name, a role
//! and quotas each), and the gRPC interceptor that identifies each call's bearer token and puts
//! its [`Caller`] in the request's extensions, where the adapters find it
//! ([`caller_of`]). What each role may do is the episode layer's edge policy
//! (`episodes::access`); this module only says who.
//!
//! Secrets are never kept: the server holds each token's SHA-256, compares the hash of the
//! presented token with every known hash in constant time, and never logs either.

use std::collections::HashSet;
use std::path::Path;
use std::sync::Arc;

use serde::Deserialize;
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use crate::types::{Caller, Role};

/// Why a token file cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("token file {path}: {reason}")]
pub struct TokensError {
    /// The file.
    pub path: String,
    /// What is wrong, and where.
    pub reason: String,
}

/// One `[[token]]` table of a token file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokenEntry {
    name: String,
    secret: Option<String>,
    secret_sha256: Option<String>,
    role: Role,
    max_episodes: Option<usize>,
    max_streams: Option<usize>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokenFile {
    #[serde(default)]
    token: Vec<TokenEntry>,
}

/// The tokens a server knows, or none (then every call is [`Caller::anonymous`]).
#[derive(Debug)]
pub struct Tokens {
    known: Vec<([u8; 32], Arc<Caller>)>,
}

/// The SHA-256 of a secret.
fn digest(secret: &[u8]) -> [u8; 32] {
    Sha256::digest(secret).into()
}

/// Whether `name` may name a token: it becomes a file name (`--records DIR/NAME.jsonl`) and a
/// metrics label.
fn valid_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.')
        && !name.starts_with('.')
}

impl Tokens {
    /// No tokens: every call is [`Caller::anonymous`] (an admin).
    pub fn open() -> Self {
        Self { known: Vec::new() }
    }

    /// `--token SECRET`: one admin token named `admin`.
    pub fn single_admin(secret: &str) -> Self {
        let caller =
            Arc::new(Caller { name: "admin".into(), role: Role::Admin, max_episodes: None, max_streams: None });
        Self { known: vec![(digest(secret.as_bytes()), caller)] }
    }

    /// Reads a token file (`--tokens`): TOML, one `[[token]]` table per client with `name`,
    /// `secret` or `secret_sha256` (64 hex digits), `role` (`agent`, `trainer` or `admin`) and
    /// the optional quotas `max_episodes` and `max_streams`.
    pub fn from_file(path: &Path) -> Result<Self, TokensError> {
        let error = |reason: String| TokensError { path: path.display().to_string(), reason };
        let text = std::fs::read_to_string(path).map_err(|e| error(e.to_string()))?;
        Self::parse(&text).map_err(error)
    }

    /// Parses a token file's text (see [`Tokens::from_file`]).
    pub fn parse(text: &str) -> Result<Self, String> {
        let file: TokenFile = toml::from_str(text).map_err(|e| e.to_string().trim_end().to_owned())?;
        if file.token.is_empty() {
            return Err("no [[token]] tables: add at least one (name, secret or secret_sha256, role)".into());
        }
        let mut names = HashSet::new();
        let mut known = Vec::with_capacity(file.token.len());
        for (i, t) in file.token.into_iter().enumerate() {
            let at = format!("token #{} ({:?})", i + 1, t.name);
            if !valid_name(&t.name) {
                return Err(format!(
                    "{at}: a name is 1 to 64 letters, digits, '-', '_' or '.', not starting with '.' (it names the token's records file)"
                ));
            }
            if !names.insert(t.name.clone()) {
                return Err(format!("{at}: the name is used twice"));
            }
            let hash = match (&t.secret, &t.secret_sha256) {
                (Some(secret), None) if !secret.trim().is_empty() => {
                    sendable_secret(secret).map_err(|why| format!("{at}: the secret {why}"))?;
                    digest(secret.as_bytes())
                }
                (Some(_), None) => return Err(format!("{at}: the secret is empty")),
                (None, Some(hex)) => parse_sha256(hex).ok_or_else(|| {
                    format!("{at}: secret_sha256 is not 64 hex digits (e.g. `printf %s SECRET | sha256sum`)")
                })?,
                (Some(_), Some(_)) => return Err(format!("{at}: give secret or secret_sha256, not both")),
                (None, None) => return Err(format!("{at}: give secret or secret_sha256")),
            };
            if known.iter().any(|(h, _): &([u8; 32], Arc<Caller>)| h == &hash) {
                return Err(format!("{at}: the same secret as another token: each token needs its own"));
            }
            for (quota, value) in [("max_episodes", t.max_episodes), ("max_streams", t.max_streams)] {
                if value == Some(0) {
                    return Err(format!("{at}: {quota} = 0 would refuse every call: leave it out for no quota"));
                }
            }
            let caller =
                Caller { name: t.name.into(), role: t.role, max_episodes: t.max_episodes, max_streams: t.max_streams };
            known.push((hash, Arc::new(caller)));
        }
        Ok(Self { known })
    }

    /// Whether calls need a token.
    pub fn required(&self) -> bool {
        !self.known.is_empty()
    }

    /// The tokens' names and roles, for the start-up log.
    pub fn summary(&self) -> Vec<String> {
        self.known.iter().map(|(_, c)| format!("{} ({})", c.name, c.role.as_str())).collect()
    }

    /// The caller presenting `authorization` (the header's value, `Bearer SECRET`), if the
    /// server knows it. Every known hash is compared, in constant time, whatever matches.
    pub fn identify(&self, authorization: Option<&[u8]>) -> Option<Arc<Caller>> {
        if self.known.is_empty() {
            return Some(Caller::anonymous());
        }
        let secret = authorization?.strip_prefix(b"Bearer ")?;
        let hash = digest(secret);
        let mut found = None;
        for (known, caller) in &self.known {
            if bool::from(known.ct_eq(&hash)) {
                found = Some(caller.clone());
            }
        }
        found
    }
}

/// Whether a client can send `secret` at all: a bearer token travels in the `authorization`
/// header, which carries printable ASCII only (0x20 to 0x7E) and no space at either end (gRPC
/// libraries refuse or trim the rest). A secret that breaks this, most often one read from a file
/// with its line break (a Kubernetes Secret made with `--from-file`), would be a token no client
/// could ever present; the error says why without quoting the secret.
pub fn sendable_secret(secret: &str) -> Result<(), String> {
    if let Some((at, c)) = secret.chars().enumerate().find(|(_, c)| !(' '..='~').contains(c)) {
        let what = match c {
            '\n' | '\r' => "a line break (read from a file with its newline?)".to_owned(),
            '\t' => "a tab".to_owned(),
            c if c.is_ascii_control() => format!("the control character U+{:04X}", u32::from(c)),
            _ => "a character that is not ASCII".to_owned(),
        };
        return Err(format!(
            "has {what} at character {}: a bearer token is printable ASCII only (a gRPC header carries nothing else)",
            at + 1
        ));
    }
    if secret.starts_with(' ') || secret.ends_with(' ') {
        return Err("starts or ends with a space, which gRPC libraries trim from a header: drop it".to_owned());
    }
    Ok(())
}

fn parse_sha256(hex: &str) -> Option<[u8; 32]> {
    let hex = hex.trim();
    if hex.len() != 64 {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

/// The gRPC interceptor: identifies the call's bearer token and puts its [`Caller`] in the
/// request's extensions; a call without a known token is UNAUTHENTICATED.
#[derive(Clone)]
pub struct TokenCheck {
    tokens: Arc<Tokens>,
}

impl TokenCheck {
    /// A check against `tokens`.
    pub fn new(tokens: Arc<Tokens>) -> Self {
        Self { tokens }
    }
}

impl tonic::service::Interceptor for TokenCheck {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        let given = request.metadata().get("authorization").map(|v| v.as_bytes());
        match self.tokens.identify(given) {
            Some(caller) => {
                request.extensions_mut().insert(caller);
                Ok(request)
            }
            None => Err(tonic::Status::unauthenticated(
                "missing or unknown bearer token: send the metadata `authorization: Bearer <token>` with a token the server knows (--token or --tokens)",
            )),
        }
    }
}

/// The caller the interceptor identified for `request`; [`Caller::anonymous`] where no
/// interceptor ran (a service embedded without one).
pub fn caller_of<T>(request: &tonic::Request<T>) -> Arc<Caller> {
    request.extensions().get::<Arc<Caller>>().cloned().unwrap_or_else(Caller::anonymous)
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = r#"
[[token]]
name = "alice"
secret = "alice-secret"
role = "agent"
max_episodes = 4
max_streams = 1

[[token]]
name = "trainer-1"
secret_sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
role = "trainer"

[[token]]
name = "root"
secret = "root-secret"
role = "admin"
"#;

    #[test]
    fn a_token_file_names_roles_and_quotas() {
        let tokens = Tokens::parse(FILE).unwrap();
        assert!(tokens.required());
        let alice = tokens.identify(Some(b"Bearer alice-secret")).unwrap();
        assert_eq!(
            (&*alice.name, alice.role, alice.max_episodes, alice.max_streams),
            ("alice", Role::Agent, Some(4), Some(1))
        );
        // sha256("test")
        let trainer = tokens.identify(Some(b"Bearer test")).unwrap();
        assert_eq!((&*trainer.name, trainer.role, trainer.max_episodes), ("trainer-1", Role::Trainer, None));
        assert_eq!(tokens.identify(Some(b"Bearer root-secret")).unwrap().role, Role::Admin);
        for wrong in
            [None, Some(&b"Bearer nope"[..]), Some(b"alice-secret"), Some(b"Bearer "), Some(b"Bearer alice-secret ")]
        {
            assert_eq!(tokens.identify(wrong), None, "{wrong:?}");
        }
        assert_eq!(tokens.summary(), ["alice (agent)", "trainer-1 (trainer)", "root (admin)"]);
    }

    #[test]
    fn open_and_single_admin_servers() {
        let open = Tokens::open();
        assert!(!open.required());
        assert_eq!(open.identify(None).unwrap().name.as_ref(), "anonymous");
        let one = Tokens::single_admin("s3cret");
        assert_eq!(one.identify(Some(b"Bearer s3cret")).unwrap().role, Role::Admin);
        assert_eq!(one.identify(Some(b"Bearer s3cre")), None);
    }

    #[test]
    fn bad_token_files_say_what_to_change() {
        let check = |text: &str, needle: &str| {
            let error = Tokens::parse(text).unwrap_err();
            assert!(error.contains(needle), "{error:?} does not contain {needle:?}");
        };
        check("", "no [[token]] tables");
        check("[[token]]\nname = \"a\"\nrole = \"agent\"\n", "give secret or secret_sha256");
        check("[[token]]\nname = \"a\"\nsecret = \"x\"\nrole = \"boss\"\n", "unknown variant `boss`");
        check("[[token]]\nname = \"../a\"\nsecret = \"x\"\nrole = \"agent\"\n", "a name is 1 to 64 letters");
        check(
            "[[token]]\nname = \"a\"\nsecret = \"x\"\nrole = \"agent\"\n[[token]]\nname = \"a\"\nsecret = \"y\"\nrole = \"agent\"\n",
            "used twice",
        );
        check(
            "[[token]]\nname = \"a\"\nsecret = \"x\"\nrole = \"agent\"\n[[token]]\nname = \"b\"\nsecret = \"x\"\nrole = \"agent\"\n",
            "the same secret",
        );
        check("[[token]]\nname = \"a\"\nsecret_sha256 = \"abc\"\nrole = \"agent\"\n", "not 64 hex digits");
        check("[[token]]\nname = \"a\"\nsecret = \"x\"\nrole = \"agent\"\nmax_episodes = 0\n", "max_episodes = 0");
        check("[[token]]\nname = \"a\"\nsecret = \"x\"\nrole = \"agent\"\nquota = 3\n", "unknown field `quota`");
        check("[[token]]\nname = \"a\"\nsecret = \" \"\nrole = \"agent\"\n", "the secret is empty");
    }
}
