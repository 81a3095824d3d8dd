//! The live web view: one page (plain HTML, CSS and JavaScript, embedded in the binary) served at
//! `/`, that talks to the REST API like any other client. Serving the page and its assets needs no
//! token (they hold no secret); every API call the page makes sends the client token, which the
//! page asks for when the API answers 401 and keeps in the tab's sessionStorage.

use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::json;

/// An embedded file: its name under /assets/, its type and its bytes.
struct Asset {
    name: &'static str,
    mime: &'static str,
    body: &'static [u8],
}

const INDEX: &[u8] = include_bytes!("assets/index.html");

const ASSETS: &[Asset] = &[
    Asset {
        name: "app.js",
        mime: "text/javascript; charset=utf-8",
        body: include_bytes!("assets/app.js"),
    },
    Asset {
        name: "app.css",
        mime: "text/css; charset=utf-8",
        body: include_bytes!("assets/app.css"),
    },
    Asset {
        name: "favicon.svg",
        mime: "image/svg+xml",
        body: include_bytes!("assets/favicon.svg"),
    },
];

/// The page's routes: `/` and `/assets/{name}`, without authentication.
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/", get(index))
        .route("/assets/{name}", get(asset))
}

/// The page may load only its own scripts and styles, and show images from blob: URLs (the API's
/// images are fetched with the token and shown through object URLs).
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; \
                   connect-src 'self'; form-action 'none'; frame-ancestors 'none'; base-uri 'none'";

fn file(mime: &'static str, body: &'static [u8]) -> Response {
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(mime)),
            // Small files, and a new binary may serve new ones: always revalidate.
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_static(CSP),
            ),
            (
                header::X_CONTENT_TYPE_OPTIONS,
                HeaderValue::from_static("nosniff"),
            ),
            (
                header::REFERRER_POLICY,
                HeaderValue::from_static("no-referrer"),
            ),
        ],
        body,
    )
        .into_response()
}

async fn index() -> Response {
    file("text/html; charset=utf-8", INDEX)
}

async fn asset(Path(name): Path<String>) -> Response {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(a) => file(a.mime, a.body),
        None => (
            StatusCode::NOT_FOUND,
            axum::Json(json!({ "error": format!("no asset '{name}'"), "field": "path" })),
        )
            .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_names_only_assets_that_exist() {
        let html = std::str::from_utf8(INDEX).expect("utf-8");
        for part in html.split("/assets/").skip(1) {
            let name: String = part
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'))
                .collect();
            assert!(
                ASSETS.iter().any(|a| a.name == name),
                "index.html names /assets/{name}, which is not embedded"
            );
        }
    }

    #[test]
    fn the_page_loads_nothing_from_elsewhere() {
        for (name, body) in
            std::iter::once(("index.html", INDEX)).chain(ASSETS.iter().map(|a| (a.name, a.body)))
        {
            let text = String::from_utf8_lossy(body);
            for bad in ["http://", "https://", "//cdn", "@import", "EventSource("] {
                // The SVG namespace is a name, not a fetch.
                let hits = text
                    .match_indices(bad)
                    .filter(|(i, _)| !text[*i..].starts_with("http://www.w3.org/"))
                    .count();
                assert_eq!(hits, 0, "{name} contains '{bad}'");
            }
        }
    }
}
