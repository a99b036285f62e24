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
