//! Optional TLS (rustls) for both services. Certificates are PEM files named in the cluster
//! YAML (coordinator) or on the worker's command line; a bad file is reported by path before
//! any connection is attempted.

use std::path::{Path, PathBuf};

use tonic::transport::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};

/// Why a TLS file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// The file could not be read.
    #[error("cannot read the TLS {what} {path}: {source}")]
    Read {
        /// certificate, key or CA.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file holds no PEM block of the expected kind.
    #[error("the TLS {what} {path} holds no PEM `{label}` block")]
    NotPem {
        /// certificate, key or CA.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The PEM label looked for.
        label: &'static str,
    },
    /// The file's PEM blocks could not be used (a damaged certificate, a key that does not
    /// match the certificate).
    #[error("the TLS {what} {path} cannot be used: {reason}")]
    Unusable {
        /// certificate, key or CA.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// `--tls-ca` was given for an address that is not `https://`.
    #[error("--tls-ca needs an https:// address, got `{address}`")]
    NotHttps {
        /// The address.
        address: String,
    },
}

/// The TLS flags of a client that dials one server (`xfactor-coordinator status`, the worker).
#[derive(Debug, Clone, Default, PartialEq, Eq, clap::Args)]
pub struct TlsClientArgs {
    /// CA certificate (PEM) to trust; turns TLS on, and the address must then be https://
    #[arg(long, value_name = "CA.pem")]
    pub tls_ca: Option<PathBuf>,
    /// Name the server's certificate must carry (by default the host of the address dialled)
    #[arg(long, value_name = "NAME", requires = "tls_ca")]
    pub tls_domain: Option<String>,
}

impl TlsClientArgs {
    /// The settings for dialling `address`: `None` without `--tls-ca`; refused when the address
    /// is not `https://`.
    pub fn client_config(
        &self,
        address: &tonic::transport::Uri,
    ) -> Result<Option<ClientTlsConfig>, TlsError> {
        let Some(ca) = &self.tls_ca else {
            return Ok(None);
        };
        if address.scheme_str() != Some("https") {
            return Err(TlsError::NotHttps {
                address: address.to_string(),
            });
        }
        let domain = match &self.tls_domain {
            Some(domain) => domain.as_str(),
            None => address.host().unwrap_or("localhost"),
        };
        client_config(ca, domain).map(Some)
    }
}

/// Makes ring the process's TLS crypto provider (once). Two providers are linked into these
/// binaries, and rustls refuses to guess between them.
fn use_ring_provider() {
    static INSTALLED: std::sync::Once = std::sync::Once::new();
    INSTALLED.call_once(|| {
        let _ = rustls::crypto::ring::default_provider().install_default();
    });
}

fn read_pem(path: &Path, what: &'static str, label: &'static str) -> Result<Vec<u8>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        what,
        path: path.to_path_buf(),
        source,
    })?;
    let text = String::from_utf8_lossy(&bytes);
    let found = text
        .lines()
        .any(|line| line.starts_with("-----BEGIN ") && line.contains(label));
    if !found {
        return Err(TlsError::NotPem {
            what,
            path: path.to_path_buf(),
            label,
        });
    }
    Ok(bytes)
}

/// A server's TLS settings from its certificate chain and private key.
pub fn server_config(cert: &Path, key: &Path) -> Result<ServerTlsConfig, TlsError> {
    use_ring_provider();
    let cert = read_pem(cert, "certificate", "CERTIFICATE")?;
    let key = read_pem(key, "key", "PRIVATE KEY")?;
    Ok(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))
}

/// A client's TLS settings: trust `ca` and expect the server to be `domain` (the name in its
/// certificate, which may differ from the address dialled).
pub fn client_config(ca: &Path, domain: &str) -> Result<ClientTlsConfig, TlsError> {
    use_ring_provider();
    let ca = read_pem(ca, "CA", "CERTIFICATE")?;
    Ok(ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(ca))
        .domain_name(domain))
}

/// The rustls settings of a ring lane's listener (the lanes run TLS themselves, outside
/// tonic): the rank's certificate chain and key, no client certificates (the dialler proves
/// the ring's secret inside the session), and no session tickets (a lane is never resumed).
pub fn lane_server_config(
    cert: &Path,
    key: &Path,
) -> Result<std::sync::Arc<rustls::ServerConfig>, TlsError> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let chain_pem = read_pem(cert, "certificate", "CERTIFICATE")?;
    let key_pem = read_pem(key, "key", "PRIVATE KEY")?;
    let unusable = |what: &'static str, path: &Path, reason: String| TlsError::Unusable {
        what,
        path: path.to_path_buf(),
        reason,
    };
    let chain = CertificateDer::pem_slice_iter(&chain_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| unusable("certificate", cert, e.to_string()))?;
    let private =
        PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| unusable("key", key, e.to_string()))?;
    let mut config = rustls::ServerConfig::builder_with_provider(lane_provider())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| unusable("certificate", cert, e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(chain, private)
        .map_err(|e| unusable("key", key, e.to_string()))?;
    config.send_tls13_tickets = 0;
    // The lane seals and opens its records itself once rustls has done the handshake.
    config.enable_secret_extraction = true;
    Ok(std::sync::Arc::new(config))
}

/// The rustls settings of a ring lane's dialler: trust the certificates `ca` signed.
pub fn lane_client_config(ca: &Path) -> Result<std::sync::Arc<rustls::ClientConfig>, TlsError> {
    use rustls::pki_types::CertificateDer;
    use rustls::pki_types::pem::PemObject;
    let ca_pem = read_pem(ca, "CA", "CERTIFICATE")?;
    let unusable = |reason: String| TlsError::Unusable {
        what: "CA",
        path: ca.to_path_buf(),
        reason,
    };
    let mut roots = rustls::RootCertStore::empty();
    for certificate in CertificateDer::pem_slice_iter(&ca_pem) {
        let certificate = certificate.map_err(|e| unusable(e.to_string()))?;
        roots
            .add(certificate)
            .map_err(|e| unusable(e.to_string()))?;
    }
    let mut config = rustls::ClientConfig::builder_with_provider(lane_provider())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| unusable(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    config.enable_secret_extraction = true;
    Ok(std::sync::Arc::new(config))
}

/// The lanes' crypto: ring, named rather than taken from the process default so that the
/// lanes' settings never depend on what else the process installed, with AES-128-GCM first
/// (10 rounds where AES-256 takes 14; a lane's cost beyond a plain one's is its cipher's and
/// its copies).
fn lane_provider() -> std::sync::Arc<rustls::crypto::CryptoProvider> {
    use rustls::crypto::ring::cipher_suite;
    std::sync::Arc::new(rustls::crypto::CryptoProvider {
        cipher_suites: vec![
            cipher_suite::TLS13_AES_128_GCM_SHA256,
            cipher_suite::TLS13_AES_256_GCM_SHA384,
            cipher_suite::TLS13_CHACHA20_POLY1305_SHA256,
        ],
        ..rustls::crypto::ring::default_provider()
    })
}

/// The URL scheme to dial a peer with.
pub fn scheme(tls: bool) -> &'static str {
    if tls { "https" } else { "http" }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn testdata(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("testdata/tls")
            .join(name)
    }

    #[test]
    fn the_test_certificates_load() {
        server_config(&testdata("server.pem"), &testdata("server.key")).unwrap();
        client_config(&testdata("ca.pem"), "localhost").unwrap();
        lane_server_config(&testdata("server.pem"), &testdata("server.key")).unwrap();
        lane_client_config(&testdata("ca.pem")).unwrap();
    }

    #[test]
    fn a_damaged_key_is_named() {
        let other_key =
            std::env::temp_dir().join(format!("xfactor-other-{}.key", std::process::id()));
        let damaged = "-----BEGIN PRIVATE KEY-----\nMAA=\n-----END PRIVATE KEY-----\n";
        std::fs::write(&other_key, damaged).unwrap();
        let refused = lane_server_config(&testdata("server.pem"), &other_key).unwrap_err();
        std::fs::remove_file(&other_key).unwrap();
        assert!(
            refused.to_string().contains(&*other_key.to_string_lossy()),
            "{refused}"
        );
    }

    #[test]
    fn a_missing_or_swapped_file_is_named() {
        let missing = server_config(&testdata("nope.pem"), &testdata("server.key")).unwrap_err();
        assert!(missing.to_string().contains("nope.pem"), "{missing}");
        let swapped = server_config(&testdata("server.key"), &testdata("server.pem")).unwrap_err();
        assert!(
            swapped.to_string().contains("server.key")
                && swapped.to_string().contains("CERTIFICATE"),
            "{swapped}"
        );
    }

    #[test]
    fn tls_flags_need_an_https_address_and_the_domain_needs_the_ca() {
        use clap::Parser;
        #[derive(Debug, Parser)]
        struct Cli {
            #[command(flatten)]
            tls: TlsClientArgs,
        }
        let ca = testdata("ca.pem");
        let cli = Cli::try_parse_from(["test", "--tls-ca", ca.to_str().unwrap()]).unwrap();
        let https = "https://127.0.0.1:50051".parse().unwrap();
        assert!(cli.tls.client_config(&https).unwrap().is_some());
        let http = "http://127.0.0.1:50051".parse().unwrap();
        let refused = cli.tls.client_config(&http).unwrap_err();
        assert!(
            refused.to_string().contains("http://127.0.0.1:50051"),
            "{refused}"
        );
        let none = Cli::try_parse_from(["test"]).unwrap();
        assert!(none.tls.client_config(&http).unwrap().is_none());
        let alone = Cli::try_parse_from(["test", "--tls-domain", "x"]).unwrap_err();
        assert!(alone.to_string().contains("--tls-ca"), "{alone}");
    }
}
