//! The gRPC contract between xfactor-dist processes, generated from `proto/xfactor.proto`, and
//! the job-token check every service applies.
//!
//! Nothing else is shared between the coordinator and the workers at run time: a change here is
//! a change of [`PROTOCOL_VERSION`], which registration compares.

pub mod auth;
pub mod convert;
pub mod tls;

pub use auth::TokenError;

/// Generated messages and services of package `xfactor.v1`.
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("xfactor.v1");
}

/// Version of the messages and their meaning. A coordinator refuses workers of another version.
pub const PROTOCOL_VERSION: u32 = 11;

/// Largest message either side accepts (a collective chunk is at most a few MiB; assignments
/// and reports are small). Anything bigger is refused before it is buffered.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// Metadata key carrying the job token.
const AUTHORIZATION: &str = "authorization";

/// Adds the job token to every outgoing request.
#[derive(Clone)]
pub struct AttachToken {
    header: tonic::metadata::MetadataValue<tonic::metadata::Ascii>,
}

impl AttachToken {
    /// Fails when the token cannot travel in an HTTP header (non-visible-ASCII characters).
    pub fn new(token: &str) -> Result<Self, TokenError> {
        let header = format!("Bearer {token}")
            .parse()
            .map_err(|_| TokenError::NotAscii)?;
        Ok(Self { header })
    }
}

impl tonic::service::Interceptor for AttachToken {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        request
            .metadata_mut()
            .insert(AUTHORIZATION, self.header.clone());
        Ok(request)
    }
}

/// Refuses every incoming request whose token differs from the job's.
#[derive(Clone)]
pub struct RequireToken {
    expected: Vec<u8>,
}

impl RequireToken {
    /// Checks requests against `token`.
    pub fn new(token: &str) -> Self {
        Self {
            expected: format!("Bearer {token}").into_bytes(),
        }
    }
}

impl tonic::service::Interceptor for RequireToken {
    fn call(&mut self, request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        match request.metadata().get(AUTHORIZATION) {
            None => Err(tonic::Status::unauthenticated(
                "missing job token: send `authorization: Bearer <token>`",
            )),
            Some(value) if constant_time_equal(value.as_bytes(), &self.expected) => Ok(request),
            Some(_) => Err(tonic::Status::unauthenticated("wrong job token")),
        }
    }
}

/// Whether `presented` equals `expected`, compared without an early exit and always over
/// `expected`'s length, so response time reveals neither how much of a guess was right nor
/// the secret's length.
pub fn constant_time_equal(presented: &[u8], expected: &[u8]) -> bool {
    let length_differs = u8::from(presented.len() != expected.len());
    expected
        .iter()
        .enumerate()
        .fold(length_differs, |diff, (i, byte)| {
            diff | (presented.get(i).copied().unwrap_or(!byte) ^ byte)
        })
        == 0
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::service::Interceptor;

    fn request_with(token: Option<&str>) -> tonic::Request<()> {
        let mut request = tonic::Request::new(());
        if let Some(token) = token {
            request = AttachToken::new(token).unwrap().call(request).unwrap();
        }
        request
    }

    #[test]
    fn the_right_token_passes_and_others_are_refused_by_name() {
        let mut check = RequireToken::new("s3cret");
        assert!(check.call(request_with(Some("s3cret"))).is_ok());
        let wrong = check.call(request_with(Some("guess"))).unwrap_err();
        assert_eq!(wrong.code(), tonic::Code::Unauthenticated);
        assert!(wrong.message().contains("wrong job token"));
        let missing = check.call(request_with(None)).unwrap_err();
        assert!(missing.message().contains("missing job token"));
    }

    #[test]
    fn comparison_needs_every_byte_and_the_length() {
        assert!(constant_time_equal(b"secret", b"secret"));
        for guess in [&b"secres"[..], b"secre", b"secrets", b"", b"Secret"] {
            assert!(!constant_time_equal(guess, b"secret"), "{guess:?}");
        }
        assert!(constant_time_equal(b"", b""));
    }

    #[test]
    fn tokens_that_cannot_be_headers_are_refused() {
        assert_eq!(AttachToken::new("a\nb").err(), Some(TokenError::NotAscii));
    }
}
