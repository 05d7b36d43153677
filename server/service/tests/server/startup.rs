//! What an operator's configuration the server refuses at start: each refusal is one line on
//! stderr naming the flag and the file at fault, status 1, no backtrace.

use std::path::Path;

/// `esrp-server ARGS` (with environment `env`) run to its end, which must be a refusal to start:
/// status 1 and one `esrp-server:` line, without a backtrace or an error chain. Returns that line.
pub(crate) fn refused_at_start(args: &[&str], env: &[(&str, &str)]) -> String {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_esrp-server"))
        .args(["--listen", "127.0.0.1:0", "--no-generate-ahead"])
        .args(args)
        .env("NODEVICE_SELECT", "1")
        .env("RUST_BACKTRACE", "1")
        .envs(env.iter().copied())
        .stdin(std::process::Stdio::null())
        .output()
        .expect("the server binary runs");
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(output.status.code(), Some(1), "{args:?}: {stderr}");
    let lines: Vec<&str> = stderr.lines().filter(|l| l.starts_with("esrp-server:")).collect();
    assert_eq!(lines.len(), 1, "{args:?}: {stderr}");
    let traced = ["backtrace", "panicked", "Caused by"].iter().any(|said| stderr.contains(said));
    assert!(!traced, "{args:?}: {stderr}");
    lines[0].to_owned()
}

fn path(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 temporary path")
}

/// A certificate file without a certificate, a key file without a key, and a key of another
/// certificate are each refused naming the flag and its file: the transport's own errors named
/// neither ("peer sent no certificates" for the server's own empty certificate file).
#[test]
fn tls_files_that_cannot_serve_are_refused_naming_their_flag() {
    let dir = tempfile::tempdir().unwrap();
    let write_pair = |name: &str| {
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_owned()]).unwrap().self_signed(&key).unwrap();
        let (cert_path, key_path) = (dir.path().join(format!("{name}.crt")), dir.path().join(format!("{name}.key")));
        std::fs::write(&cert_path, cert.pem()).unwrap();
        std::fs::write(&key_path, key.serialize_pem()).unwrap();
        (cert_path, key_path)
    };
    let (cert, key) = write_pair("a");
    let (other_cert, _) = write_pair("b");
    let empty = dir.path().join("empty.pem");
    std::fs::write(&empty, "").unwrap();
    let cases = [
        ((&empty, &key), format!("--tls-cert {}: no certificate in it", path(&empty))),
        ((&cert, &empty), format!("--tls-key {}: no private key in it", path(&empty))),
        ((&cert, &cert), format!("--tls-key {}: no private key in it", path(&cert))),
        ((&other_cert, &key), format!("--tls-key {} is not the key of --tls-cert {}", path(&key), path(&other_cert))),
    ];
    for ((cert, key), said) in cases {
        let line = refused_at_start(&["--tls-cert", path(cert), "--tls-key", path(key)], &[]);
        assert!(line.starts_with(&format!("esrp-server: {said}")), "{line}");
    }
}

/// A secret no client could send (a bearer header is printable ASCII, with no space at either
/// end) is refused at start, without being quoted: most often a token read from a file with its
/// line break, as from a Kubernetes Secret made with `--from-file`. Such a server used to start
/// and answer UNAUTHENTICATED to every call.
#[test]
fn a_token_no_client_could_send_is_refused() {
    let line = refused_at_start(&[], &[("ESRP_TOKEN", "s3cret-from-a-file\n")]);
    assert!(
        line.starts_with("esrp-server: --token (ESRP_TOKEN): the token has a line break (read from a file"),
        "{line}"
    );
    assert!(!line.contains("s3cret"), "the secret is not quoted: {line}");

    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tokens.toml");
    for (secret, said) in [
        ("team\\n", "has a line break"),
        ("t\u{e9}am-secret", "has a character that is not ASCII"),
        ("team-secret ", "starts or ends with a space"),
    ] {
        let text = format!(
            "[[token]]\nname = \"ops\"\nsecret = \"ops-secret\"\nrole = \"admin\"\n\n[[token]]\nname = \"team\"\nsecret = \"{secret}\"\nrole = \"agent\"\n"
        );
        std::fs::write(&file, text).unwrap();
        let line = refused_at_start(&["--tokens", path(&file)], &[]);
        let expected = format!("esrp-server: token file {}: token #2 (\"team\"): the secret {said}", path(&file));
        assert!(line.starts_with(&expected), "{line}");
    }
}

/// A records folder the server could not record in is refused at start: a file in its place
/// (it used to say "cannot create it: File exists"), and a folder it cannot write in, which it
/// used to serve with, losing every record (logged) as its episode ended.
#[test]
fn a_records_folder_that_cannot_take_records_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("records");
    std::fs::write(&file, "").unwrap();
    let line = refused_at_start(&["--records", path(&file)], &[]);
    assert!(line.starts_with(&format!("esrp-server: --records {}: not a folder", path(&file))), "{line}");

    // A folder no one may create a file in, whoever runs the tests (root included); the key is
    // given, so the server only reads it.
    let key = dir.path().join("records.key");
    std::fs::write(&key, "0123456789abcdef0123456789abcdef").unwrap();
    let unwritable = "/proc/self/fdinfo";
    let line = refused_at_start(&["--records", unwritable, "--records-key", path(&key), "--record", "all"], &[]);
    assert!(line.starts_with(&format!("esrp-server: --records {unwritable}: cannot write in it")), "{line}");
}

/// A records folder kept for one challenge is refused to a server of another (another challenge
/// seed here), before anything in it is read or written: its counted attempts would refuse the
/// new challenge's scenes of the same ids as played already, and its scene list, overwritten,
/// would no longer verify its records. The same challenge restarted is served as before.
#[tokio::test]
async fn a_records_folder_of_another_challenge_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    {
        let server = super::challenge::start(dir.path(), &[]);
        let mut bob = super::challenge::client(&server, "bob-secret").await;
        let created = bob.create_episode(super::challenge::create("challenge/00000", false)).await.unwrap();
        let episode_id = created.into_inner().episode_id;
        bob.close_episode(esrp_server::proto::CloseEpisodeRequest { episode_id }).await.unwrap();
    }
    let records = dir.path().join("records");
    let contents = || -> Vec<Vec<u8>> {
        ["challenge-scenes.json", "bob.jsonl", "attempts.journal"]
            .iter()
            .map(|name| std::fs::read(records.join(name)).unwrap())
            .collect()
    };
    let before = contents();
    let tokens = dir.path().join("tokens.toml");
    let args = |seed| {
        vec![
            "--tokens",
            path(&tokens),
            "--challenge-seed",
            seed,
            "--challenge-scenes",
            "3",
            "--minival-scenes",
            "1",
            "--records",
            path(&records),
        ]
    };
    let line = refused_at_start(&args("another-seed-of-another-challenge"), &[]);
    let said = format!("esrp-server: --records {}: it holds the records of another challenge", path(&records));
    assert!(line.starts_with(&said), "{line}");
    assert!(before == contents(), "the folder is left as it was");
    let again = super::challenge::start(dir.path(), &[]);
    let mut bob = super::challenge::client(&again, "bob-secret").await;
    let replayed = bob.create_episode(super::challenge::create("challenge/00000", false)).await;
    super::challenge::refused(replayed, tonic::Code::FailedPrecondition, "already played");
}
