//! The browser client (`client/` at the repository root), compiled into the binary so that
//! the master serves it with no files beside it. Only the files listed here are served:
//! a request can never reach anything else on disk.

use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};

const FILES: &[(&str, &str, &str)] = &[
    ("index.html", "text/html; charset=utf-8", include_str!("../../client/index.html")),
    ("nephele.js", "text/javascript; charset=utf-8", include_str!("../../client/nephele.js")),
    ("style.css", "text/css; charset=utf-8", include_str!("../../client/style.css")),
    ("PROTOCOL.md", "text/markdown; charset=utf-8", include_str!("../../client/PROTOCOL.md")),
];

/// The named client file, or 404.
pub fn serve(name: &str) -> Response {
    match FILES.iter().find(|(file, _, _)| *file == name) {
        Some((_, content_type, body)) => {
            ([(header::CONTENT_TYPE, *content_type), (header::CACHE_CONTROL, "no-cache")], *body).into_response()
        }
        None => (StatusCode::NOT_FOUND, "no such client file").into_response(),
    }
}
