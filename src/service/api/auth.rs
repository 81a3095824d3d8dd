//! Bearer tokens: the client routes' (one client token, or per-user tokens from a users file)
//! and the worker routes' (`/v1/worker/*`). A client request's token resolves to a `Principal`
//! (its user's name and role), which the handlers get as a request extension and ask
//! `may_act_on` / `require_admin` before changing anything.

use super::AppState;
use super::errors::ApiError;
use crate::protocol::Role;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

/// The name of the client token's user, and of every request when no client token is set.
pub(crate) const ADMIN: &str = "admin";

/// Whom a client request acts for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Principal {
    pub name: String,
    pub role: Role,
}

impl Principal {
    /// The admin of the single client token (or of a server without one).
    pub fn admin() -> Principal {
        Principal {
            name: ADMIN.to_string(),
            role: Role::Admin,
        }
    }
}

/// A user of `omis serve --users`: a name, a role, and the SHA-256 of its token.
#[derive(Clone, Debug)]
pub(crate) struct User {
    pub name: String,
    pub role: Role,
    token_sha256: [u8; 32],
}

/// An entry of the users file as written.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct UserEntry {
    name: String,
    role: Role,
    #[serde(default)]
    token: Option<String>,
    #[serde(default)]
    token_sha256: Option<String>,
}

/// Longest user name.
const MAX_NAME: usize = 64;

/// The users of a users file (JSON: `[{"name", "role": "admin"|"user", "token" or
/// "token_sha256"}]`); the error names the entry and its field.
pub(crate) fn parse_users(text: &str) -> Result<Vec<User>, String> {
    let de = &mut serde_json::Deserializer::from_str(text);
    let entries: Vec<UserEntry> = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        format!("at {path}: {}", e.inner())
    })?;
    if entries.is_empty() {
        return Err("the file lists no user".into());
    }
    let mut users: Vec<User> = Vec::with_capacity(entries.len());
    for (i, e) in entries.into_iter().enumerate() {
        let at = |field: &str, what: &str| format!("entry {i} (\"{}\"): {field}: {what}", e.name);
        if e.name.is_empty()
            || e.name.len() > MAX_NAME
            || !e
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | '@'))
        {
            return Err(at("name", "1 to 64 letters, digits, '-', '_', '.' or '@'"));
        }
        if users.iter().any(|u| u.name == e.name) {
            return Err(at("name", "a second user of this name"));
        }
        let token_sha256 = match (&e.token, &e.token_sha256) {
            (Some(t), None) => {
                if t.len() < 8 || t.chars().any(|c| c.is_whitespace() || c.is_control()) {
                    return Err(at(
                        "token",
                        "at least 8 characters, no white space or control characters",
                    ));
                }
                Sha256::digest(t.as_bytes()).into()
            }
            (None, Some(h)) => parse_sha256(h).ok_or_else(|| {
                at(
                    "token_sha256",
                    "64 hexadecimal digits (SHA-256 of the token)",
                )
            })?,
            _ => return Err(at("token", "give exactly one of token and token_sha256")),
        };
        if users.iter().any(|u| u.token_sha256 == token_sha256) {
            return Err(at("token", "the same token as an earlier user"));
        }
        users.push(User {
            name: e.name,
            role: e.role,
            token_sha256,
        });
    }
    Ok(users)
}

fn parse_sha256(hex: &str) -> Option<[u8; 32]> {
    if hex.len() != 64 {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

/// The bearer token of `headers`: None without one; an error when the header is there but is
/// not `Bearer <token>`.
fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            // The scheme is case-insensitive (RFC 9110, section 11.1); the token is compared as
            // sent, after exactly one space: nothing is trimmed from it.
            let (scheme, token) = v.split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then_some(token)
        })
}

fn missing() -> ApiError {
    ApiError::field(
        StatusCode::UNAUTHORIZED,
        "Authorization",
        "missing bearer token (Authorization: Bearer <token>)",
    )
}

fn invalid() -> ApiError {
    ApiError::field(
        StatusCode::UNAUTHORIZED,
        "Authorization",
        "invalid bearer token",
    )
}

/// Checks `Authorization: Bearer <token>` against `want` (None: nothing to check).
fn check_token(headers: &HeaderMap, want: &Option<String>) -> Result<(), ApiError> {
    let Some(want) = want else {
        return Ok(());
    };
    match bearer(headers) {
        Some(t) if constant_time_eq(t.as_bytes(), want.as_bytes()) => Ok(()),
        Some(_) => Err(invalid()),
        None => Err(missing()),
    }
}

/// Whom a client request acts for: the user whose token it sends, the admin for the single
/// client token, or the admin when no client token and no users are set. Every user's digest
/// is compared in full, whichever matches.
fn resolve_client(
    headers: &HeaderMap,
    client_token: &Option<String>,
    users: &[User],
) -> Result<Principal, ApiError> {
    if client_token.is_none() && users.is_empty() {
        return Ok(Principal::admin());
    }
    let Some(got) = bearer(headers) else {
        return Err(missing());
    };
    let mut found: Option<Principal> = None;
    if let Some(want) = client_token
        && constant_time_eq(got.as_bytes(), want.as_bytes())
    {
        found = Some(Principal::admin());
    }
    if !users.is_empty() {
        let digest: [u8; 32] = Sha256::digest(got.as_bytes()).into();
        for u in users {
            if constant_time_eq(&digest, &u.token_sha256) && found.is_none() {
                found = Some(Principal {
                    name: u.name.clone(),
                    role: u.role,
                });
            }
        }
    }
    found.ok_or_else(invalid)
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Whether `p` may change a job owned by `owner` (None: a job without an owner, which only an
/// admin may change): an admin may change every job, a user its own.
pub(crate) fn may_act_on(p: &Principal, owner: Option<&str>) -> bool {
    p.role == Role::Admin || owner == Some(p.name.as_str())
}

/// `may_act_on` as the API's answer: 403 naming the job and its owner when `p` may not act on
/// job `id`.
pub(crate) fn require_owner(p: &Principal, id: &str, owner: Option<&str>) -> Result<(), ApiError> {
    if may_act_on(p, owner) {
        return Ok(());
    }
    let whose = match owner {
        Some(o) => format!("user '{o}'"),
        None => "no user (only an admin may act on it)".to_string(),
    };
    Err(ApiError::field(
        StatusCode::FORBIDDEN,
        "id",
        format!(
            "user '{}' may not act on job '{id}': it belongs to {whose}",
            p.name
        ),
    ))
}

/// 403 unless `p` is an admin (worker actions, and whatever acts on every job).
pub(crate) fn require_admin(p: &Principal) -> Result<(), ApiError> {
    if p.role == Role::Admin {
        return Ok(());
    }
    Err(ApiError::field(
        StatusCode::FORBIDDEN,
        "Authorization",
        format!(
            "user '{}' is not an admin; this action is an admin's",
            p.name
        ),
    ))
}

/// Middleware of the client routes: resolves the token to a `Principal`, which it adds to the
/// request's extensions.
pub(crate) async fn client_auth(
    State(app): State<AppState>,
    mut req: Request,
    next: Next,
) -> Response {
    match resolve_client(req.headers(), &app.cfg.client_token, &app.cfg.users) {
        Ok(p) => {
            req.extensions_mut().insert(p);
            next.run(req).await
        }
        Err(e) => e.into_response(),
    }
}

/// Middleware of the worker routes.
pub(crate) async fn worker_auth(State(app): State<AppState>, req: Request, next: Next) -> Response {
    match check_token(req.headers(), &app.cfg.worker_token) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_token(t: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(
            header::AUTHORIZATION,
            format!("Bearer {t}").parse().expect("header"),
        );
        h
    }

    #[test]
    fn tokens_resolve_to_their_users_and_roles() {
        let hash = hex(&Sha256::digest(b"bob-secret-1"));
        let users = parse_users(&format!(
            r#"[{{"name": "ana", "token": "ana-secret-1", "role": "admin"}},
                {{"name": "bob", "token_sha256": "{hash}", "role": "user"}}]"#
        ))
        .expect("users");
        let single = Some("single-token".to_string());
        let who = |t: &str| resolve_client(&with_token(t), &single, &users);
        assert_eq!(who("ana-secret-1").expect("ana").name, "ana");
        let bob = who("bob-secret-1").expect("bob");
        assert_eq!((bob.name.as_str(), bob.role), ("bob", Role::User));
        assert_eq!(who("single-token").expect("admin"), Principal::admin());
        assert_eq!(
            who("nobody-at-all").expect_err("refused").status,
            StatusCode::UNAUTHORIZED
        );
        assert!(resolve_client(&HeaderMap::new(), &single, &users).is_err());
        assert_eq!(
            resolve_client(&HeaderMap::new(), &None, &[]).expect("open"),
            Principal::admin()
        );
        assert!(may_act_on(&bob, Some("bob")));
        assert!(!may_act_on(&bob, Some("ana")));
        assert!(!may_act_on(&bob, None));
        assert!(may_act_on(&Principal::admin(), Some("bob")));
        assert!(require_admin(&bob).is_err());
    }

    #[test]
    fn a_bad_users_file_names_the_entry_and_field() {
        for (text, want) in [
            ("{}", "at"),
            ("[]", "no user"),
            (
                r#"[{"name": "a", "role": "boss", "token": "12345678"}]"#,
                "[0].role",
            ),
            (
                r#"[{"name": "a", "role": "user"}]"#,
                "entry 0 (\"a\"): token",
            ),
            (
                r#"[{"name": "a", "role": "user", "token_sha256": "abc"}]"#,
                "entry 0 (\"a\"): token_sha256",
            ),
            (
                r#"[{"name": "a", "role": "user", "token": "12345678"},
                    {"name": "a", "role": "user", "token": "87654321"}]"#,
                "entry 1 (\"a\"): name",
            ),
            (
                r#"[{"name": "a b", "role": "user", "token": "12345678"}]"#,
                "entry 0 (\"a b\"): name",
            ),
        ] {
            let e = parse_users(text).expect_err(text);
            assert!(e.contains(want), "{text}: {e}");
        }
    }

    fn hex(b: &[u8]) -> String {
        b.iter().map(|x| format!("{x:02x}")).collect()
    }
}
