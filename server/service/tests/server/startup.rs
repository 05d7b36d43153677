//! What an operator's configuration the server refuses at start: each refusal is one line on
//! stderr naming the flag and the file at fault, status 1, no backtrace.

use std::path::Path;

/// `esrp-server ARGS` (with environment `env`) run to its end, which must be a refusal to start:
/// status 1 and one `esrp-server:` line, without a backtrace. Returns that line.
fn refused_at_start(args: &[&str], env: &[(&str, &str)]) -> String {
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
    assert!(!stderr.contains("backtrace") && !stderr.contains("panicked"), "{args:?}: {stderr}");
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
