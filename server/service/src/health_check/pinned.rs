//! TLS that trusts exactly one certificate: the check of a server by its own configuration
//! (`--tls-cert`), as its container runs it. The server is known by the certificate it serves,
//! byte for byte, and proves it holds its key in the handshake; neither the certificate's names
//! (the check asks on loopback, which they rarely include) nor its kind (OpenSSL's
//! `req -x509` makes a CA certificate, which web PKI refuses as a server's) matter.

use std::sync::Arc;

use anyhow::{Context, anyhow};
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, WebPkiSupportedAlgorithms};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};
use tonic::transport::{Channel, Endpoint, Uri};

/// Accepts the server whose end-entity certificate is `certificate`.
#[derive(Debug)]
struct ThisCertificate {
    certificate: CertificateDer<'static>,
    algorithms: WebPkiSupportedAlgorithms,
}

impl ServerCertVerifier for ThisCertificate {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        if end_entity.as_ref() == self.certificate.as_ref() {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::General("the server's certificate is not the one in --tls-cert".into()))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(message, cert, dss, &self.algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.algorithms.supported_schemes()
    }
}

/// A TLS client configuration (HTTP/2) that trusts only the first certificate of the PEM chain
/// at `path`.
pub fn config(path: &std::path::Path) -> anyhow::Result<Arc<rustls::ClientConfig>> {
    let certificate = CertificateDer::pem_file_iter(path)
        .and_then(|mut certificates| certificates.next().transpose())
        .map_err(|e| anyhow!("{e:?}"))
        .with_context(|| format!("cannot read the server's --tls-cert {}", path.display()))?
        .ok_or_else(|| anyhow!("the server's --tls-cert {} holds no certificate", path.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier = ThisCertificate { certificate, algorithms: provider.signature_verification_algorithms };
    let mut config = rustls::ClientConfig::builder_with_provider(provider as Arc<CryptoProvider>)
        .with_safe_default_protocol_versions()?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(verifier))
        .with_no_client_auth();
    config.alpn_protocols = vec![b"h2".to_vec()];
    Ok(Arc::new(config))
}

/// Connects to `host_port` over TLS with `config`.
pub async fn connect(host_port: &str, config: Arc<rustls::ClientConfig>) -> anyhow::Result<Channel> {
    let endpoint = Endpoint::from_shared(format!("http://{host_port}"))
        .map_err(|e| anyhow!("{host_port:?} is not an address: {e}"))?;
    let connector = tokio_rustls::TlsConnector::from(config);
    let channel = endpoint
        .connect_with_connector(tower::service_fn(move |uri: Uri| {
            let connector = connector.clone();
            async move {
                let host = uri.host().unwrap_or_default().trim_start_matches('[').trim_end_matches(']').to_owned();
                let port = uri.port_u16().unwrap_or(443);
                let tcp = tokio::net::TcpStream::connect((host.as_str(), port)).await?;
                tcp.set_nodelay(true)?;
                let name = ServerName::try_from(host).map_err(std::io::Error::other)?;
                let tls = connector.connect(name, tcp).await?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(tls))
            }
        }))
        .await?;
    Ok(channel)
}
