//! The HTTP side: the page and its scripts (embedded in the binary; nothing is read from
//! disk by path), the scene description, the training photos by index, and the WebSocket
//! each page opens. When the server listens beyond this machine every request must carry
//! the viewer's random token (`?token=`).

use std::sync::Arc;

use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::Deserialize;

use crate::protocol::MAX_MESSAGE_BYTES;
use crate::state::Viewer;

const INDEX_HTML: &str = include_str!("../assets/index.html");
const VIEWER_JS: &str = include_str!("../assets/viewer.js");
const STYLE_CSS: &str = include_str!("../assets/style.css");

#[derive(Deserialize)]
struct Access {
    token: Option<String>,
}

/// The refusal of a request without the viewer's token (when it has one).
fn refusal(viewer: &Viewer, access: &Access) -> Option<Response> {
    match &viewer.token {
        Some(t) if access.token.as_deref() != Some(t.as_str()) => Some(
            (
                StatusCode::FORBIDDEN,
                "this viewer needs the token printed by `nerf view` (open the address it printed)",
            )
                .into_response(),
        ),
        _ => None,
    }
}

fn asset(kind: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, kind)], body).into_response()
}

async fn index(State(v): State<Arc<Viewer>>, Query(a): Query<Access>) -> Response {
    if let Some(r) = refusal(&v, &a) {
        return r;
    }
    asset("text/html; charset=utf-8", INDEX_HTML)
}

async fn scene(State(v): State<Arc<Viewer>>, Query(a): Query<Access>) -> Response {
    if let Some(r) = refusal(&v, &a) {
        return r;
    }
    let mut info = v.info.clone();
    if let Ok(run) = v.model.run.read() {
        info.step = run.step;
    }
    Json(info).into_response()
}

async fn photo(
    State(v): State<Arc<Viewer>>,
    Path(index): Path<String>,
    Query(a): Query<Access>,
) -> Response {
    if let Some(r) = refusal(&v, &a) {
        return r;
    }
    let Ok(index) = index.parse::<usize>() else {
        return (
            StatusCode::BAD_REQUEST,
            format!("photo {index:?}: expected a training image's index"),
        )
            .into_response();
    };
    let viewer = v.clone();
    match tokio::task::spawn_blocking(move || viewer.photo(index)).await {
        Ok(Ok(jpeg)) => ([(header::CONTENT_TYPE, "image/jpeg")], jpeg).into_response(),
        Ok(Err(e)) => (StatusCode::NOT_FOUND, e).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

async fn socket(
    State(v): State<Arc<Viewer>>,
    Query(a): Query<Access>,
    ws: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Response {
    // The token first: a request without it learns nothing, not even what it lacks.
    if let Some(r) = refusal(&v, &a) {
        return r;
    }
    let ws = match ws {
        Ok(ws) => ws,
        Err(rejection) => return rejection.into_response(),
    };
    ws.max_message_size(MAX_MESSAGE_BYTES)
        .max_frame_size(MAX_MESSAGE_BYTES)
        .on_upgrade(move |socket| crate::session::run(v, socket))
}

/// The viewer's routes.
pub fn router(viewer: Arc<Viewer>) -> Router {
    Router::new()
        .route("/", get(index))
        .route(
            "/viewer.js",
            get(|| async { asset("text/javascript; charset=utf-8", VIEWER_JS) }),
        )
        .route(
            "/style.css",
            get(|| async { asset("text/css; charset=utf-8", STYLE_CSS) }),
        )
        .route("/api/scene", get(scene))
        .route("/api/photo/{index}", get(photo))
        .route("/ws", get(socket))
        .with_state(viewer)
}
