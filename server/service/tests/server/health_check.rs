//! `esrp-server health-check` (the container HEALTHCHECK) against the real binary: SERVING is exit
//! 0; a closed port, a port that never answers, an unknown service or the wrong protocol is exit
//! 1 with a one-line reason.

use std::process::{Command, Output};

use super::harness::Server;

/// Runs `esrp-server health-check ARGS` with `env` and none of the caller's `ESRP_*` variables.
fn health_check(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_esrp-server"));
    command.arg("health-check").args(args);
    for (name, _) in std::env::vars_os().filter(|(name, _)| name.to_string_lossy().starts_with("ESRP_")) {
        command.env_remove(name);
    }
    command.envs(env.iter().copied());
    command.output().expect("esrp-server runs")
}

/// Checks the exit status and that stdout (on success) or stderr (on failure) is one line
/// containing `expected`.
fn check(output: &Output, serving: bool, expected: &str) {
    let (stdout, stderr) = (String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    let said = if serving { &stdout } else { &stderr };
    assert_eq!(output.status.code(), Some(if serving { 0 } else { 1 }), "stdout: {stdout}\nstderr: {stderr}");
    assert_eq!(said.lines().count(), 1, "one line: {said:?}");
    assert!(said.contains(expected), "{expected:?} in {said:?}");
}

/// The `HOST:PORT` of a server's `http://HOST:PORT` address.
fn host_port(server: &Server) -> String {
    server.address.trim_start_matches("http://").to_owned()
}

#[test]
fn a_running_server_is_serving_even_with_a_token() {
    let server = Server::start(&["--token", "secret"]);
    let address = host_port(&server);
    check(&health_check(&[&address], &[]), true, "the server is SERVING");
    check(&health_check(&[&server.address], &[]), true, "SERVING");
    // The default address is the server's own ESRP_LISTEN, 0.0.0.0 asked on loopback.
    let port = address.rsplit(':').next().unwrap();
    check(&health_check(&[], &[("ESRP_LISTEN", &format!("0.0.0.0:{port}"))]), true, "http://127.0.0.1:");
    // Each service by name; an unknown one is NOT_FOUND.
    for service in ["esrp.v1.Esrp", "dm_env_rpc.v1.Environment"] {
        check(&health_check(&["--service", service, &address], &[]), true, "is SERVING");
    }
    check(&health_check(&["--service", "nope", &address], &[]), false, "NotFound");
    // TLS against a plaintext server fails.
    let pem = tempfile::NamedTempFile::new().unwrap();
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap().cert;
    std::fs::write(pem.path(), cert.pem()).unwrap();
    check(&health_check(&["--tls-ca", pem.path().to_str().unwrap(), &address], &[]), false, "cannot connect");
}

#[test]
fn a_closed_port_or_a_silent_one_is_unhealthy() {
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().to_string();
    check(&health_check(&[&closed], &[]), false, "cannot connect");
    // A listener that accepts connections (the kernel does) but never speaks HTTP/2.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = silent.local_addr().unwrap().to_string();
    let started = std::time::Instant::now();
    check(&health_check(&["--timeout-ms", "300", &address], &[]), false, "no answer within 300 ms");
    assert!(started.elapsed() < std::time::Duration::from_secs(10), "{:?}", started.elapsed());
    check(&health_check(&["ftp://127.0.0.1:1"], &[]), false, "unknown scheme");
}

/// Inside a TLS server's container the check speaks TLS and trusts exactly the server's own
/// certificate (ESRP_TLS_CERT), whatever names it carries (the check asks on 127.0.0.1) and even
/// when it is a CA certificate (what `openssl req -x509` makes by default, which web PKI refuses
/// as a server's); with a name to verify given, it checks as any client would.
#[test]
fn a_tls_server_is_checked_over_tls_with_its_own_certificate() {
    let dir = tempfile::tempdir().unwrap();
    for ca_certificate in [false, true] {
        let key = rcgen::KeyPair::generate().unwrap();
        let mut params = rcgen::CertificateParams::new(vec!["localhost".to_owned()]).unwrap();
        if ca_certificate {
            params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
        }
        let cert = params.self_signed(&key).unwrap();
        let (cert_path, key_path) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
        std::fs::write(&cert_path, cert.pem()).unwrap();
        std::fs::write(&key_path, key.serialize_pem()).unwrap();
        let (cert_path, key_path) = (cert_path.to_str().unwrap(), key_path.to_str().unwrap());
        let server = Server::start(&["--tls-cert", cert_path, "--tls-key", key_path]);
        let address = host_port(&server);
        let env = [("ESRP_TLS_CERT", cert_path), ("ESRP_TLS_KEY", key_path)];
        check(&health_check(&[&address], &env), true, "https://127.0.0.1");
        check(&health_check(&[], &[env[0], env[1], ("ESRP_LISTEN", &address)]), true, "SERVING");
        // With a name to verify, the certificate is checked as any client would check it.
        let named = health_check(&["--tls-domain", "localhost", &address], &env);
        if ca_certificate {
            check(&named, false, "CaUsedAsEndEntity");
        } else {
            check(&named, true, "SERVING");
        }
        check(&health_check(&["--tls-domain", "elsewhere", &address], &env), false, "invalid peer certificate");
        // Another certificate than the server's is refused; plaintext gets no answer.
        let other = dir.path().join("other.pem");
        std::fs::write(&other, rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap().cert.pem())
            .unwrap();
        let other = other.to_str().unwrap();
        check(&health_check(&[&address], &[("ESRP_TLS_CERT", other)]), false, "not the one in --tls-cert");
        check(&health_check(&[&format!("http://{address}")], &env), false, "http://");
    }
}
