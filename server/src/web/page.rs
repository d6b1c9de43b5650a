//! The live page at `/`: the built files (`web/dist`, assembled by
//! `npm ci` in `web/`) when they exist, otherwise a short page that says which
//! command builds them, so that a person who starts the server with
//! `--web-addr` before building learns what is missing from the browser
//! as well as from the log. The WebSocket works either way.

use std::path::Path;

use axum::http::StatusCode;
use axum::response::{Html, IntoResponse, Response};
use axum::Router;
use tower_http::services::ServeDir;

/// The command that builds the page, from the repository root.
pub const BUILD_COMMAND: &str = "cd web && npm ci";

/// What `/` serves: `dir` (index.html at `/`, 404 for a missing file) if
/// it holds a built page; otherwise every path answers the build hint,
/// and the log says so once, now.
pub fn service(dir: &Path) -> Router {
    if dir.join("index.html").is_file() {
        tracing::info!(dir = %dir.display(), "web: serving the live page");
        return Router::new().fallback_service(ServeDir::new(dir));
    }
    tracing::warn!(
        dir = %dir.display(),
        "web: the live page is not built ({} has no index.html); build it with `{BUILD_COMMAND}` \
         (the WebSocket works without it)",
        dir.display()
    );
    let body = missing_page(dir);
    Router::new().fallback(move || {
        let body = body.clone();
        async move { not_built(body) }
    })
}

fn not_built(body: String) -> Response {
    (StatusCode::SERVICE_UNAVAILABLE, Html(body)).into_response()
}

/// The page that stands in for the missing build.
fn missing_page(dir: &Path) -> String {
    format!(
        "<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>blapose: page not built</title></head>\n\
         <body><h1>The live page is not built</h1>\n\
         <p><code>{}</code> has no <code>index.html</code>. Build it from the repository root with</p>\n\
         <pre>{BUILD_COMMAND}</pre>\n<p>and reload. The WebSocket at <code>{}</code> works without it.</p>\
         </body></html>\n",
        escape(&dir.display().to_string()),
        super::STREAM_PATH,
    )
}

/// `text` safe inside HTML.
fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hint_names_the_command_and_escapes_the_path() {
        let page = missing_page(Path::new("a<b>/dist"));
        assert!(page.contains(BUILD_COMMAND));
        assert!(page.contains("a&lt;b&gt;/dist"));
        assert!(!page.contains("a<b>"));
    }
}
