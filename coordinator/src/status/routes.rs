//! The status page's routes on the metrics port: `/` (the page, or a form asking for the job
//! token), `POST /login` (the token, answered with a session cookie), and `/api/status` (the
//! same snapshot as JSON, for the cookie or `Authorization: Bearer <token>`). Nothing of the
//! job is shown without the token; the cookie is a random session value, never the token.

use std::sync::Arc;
use std::time::Instant;

use axum::Form;
use axum::Router;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{Html, IntoResponse, Redirect, Response};
use serde::Deserialize;
use tokio::sync::Mutex;

use super::page;
use crate::job::JobState;

/// The session cookie's name.
const COOKIE: &str = "xfactor_status";

/// What the routes share: the job, the tokens that open the page and the session value given
/// for them.
#[derive(Clone)]
struct Viewing {
    state: Arc<Mutex<JobState>>,
    tokens: Arc<[String]>,
    session: Arc<str>,
}

/// Why the routes could not be set up.
#[derive(Debug, thiserror::Error)]
#[error("no random session value for the status page: {0}")]
pub struct NoSession(String);

/// The status page's routes over the job `state`, shown to holders of the job's `token` or of
/// the read-only `viewing` token.
pub fn routes(
    state: Arc<Mutex<JobState>>,
    token: &str,
    viewing: Option<&str>,
) -> Result<Router, NoSession> {
    let mut random = [0u8; 24];
    getrandom::fill(&mut random).map_err(|e| NoSession(e.to_string()))?;
    let session: String = random.iter().map(|b| format!("{b:02x}")).collect();
    let tokens: Vec<String> = std::iter::once(token)
        .chain(viewing)
        .map(str::to_string)
        .collect();
    let viewing = Viewing {
        state,
        tokens: tokens.into(),
        session: session.into(),
    };
    Ok(Router::new()
        .route("/", axum::routing::get(page_or_login))
        .route("/login", axum::routing::post(login))
        .route("/api/status", axum::routing::get(api_status))
        .with_state(viewing))
}

/// Equality that takes as long whatever the first difference.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Viewing {
    /// Whether `given` is one of the tokens that open the page.
    fn opens(&self, given: &str) -> bool {
        self.tokens.iter().fold(false, |found, token| {
            found | same(given.as_bytes(), token.as_bytes())
        })
    }

    /// Whether `headers` carry the session cookie or a token as a bearer.
    fn admits(&self, headers: &HeaderMap) -> bool {
        let cookie = headers
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|value| value.to_str().ok())
            .flat_map(|value| value.split(';'))
            .filter_map(|pair| pair.trim().split_once('='))
            .any(|(name, value)| name == COOKIE && same(value.as_bytes(), self.session.as_bytes()));
        let bearer = headers
            .get(header::AUTHORIZATION)
            .and_then(|value| value.to_str().ok())
            .and_then(|value| value.strip_prefix("Bearer "))
            .is_some_and(|token| self.opens(token.trim()));
        cookie || bearer
    }

    async fn snapshot(&self) -> crate::job::snapshot::StatusSnapshot {
        self.state.lock().await.snapshot(Instant::now())
    }
}

async fn page_or_login(State(viewing): State<Viewing>, headers: HeaderMap) -> Response {
    if !viewing.admits(&headers) {
        return (StatusCode::UNAUTHORIZED, Html(page::login(None))).into_response();
    }
    Html(page::render(&viewing.snapshot().await)).into_response()
}

#[derive(Deserialize)]
struct Login {
    token: String,
}

async fn login(State(viewing): State<Viewing>, Form(form): Form<Login>) -> Response {
    if !viewing.opens(&form.token) {
        tracing::warn!("status page: a wrong token was entered");
        let page = page::login(Some("That is not this job's token."));
        return (StatusCode::UNAUTHORIZED, Html(page)).into_response();
    }
    // Lax, so that the page opens from a link or a bookmark: the page only reads, so the
    // cross-site requests Lax lets through (top-level GETs) change nothing.
    let cookie = format!(
        "{COOKIE}={}; Path=/; HttpOnly; SameSite=Lax",
        viewing.session
    );
    ([(header::SET_COOKIE, cookie)], Redirect::to("/")).into_response()
}

async fn api_status(State(viewing): State<Viewing>, headers: HeaderMap) -> Response {
    let json = [(header::CONTENT_TYPE, "application/json")];
    if !viewing.admits(&headers) {
        let refusal = r#"{"error":"this job's token is needed (Authorization: Bearer)"}"#;
        return (StatusCode::UNAUTHORIZED, json, refusal).into_response();
    }
    // A snapshot is plain strings and numbers: serialising it cannot fail.
    let body = serde_json::to_string(&viewing.snapshot().await).unwrap_or_default();
    (json, body).into_response()
}
