//! One page's WebSocket: requests in, frames and answers out. Rendering runs on a worker
//! thread of its own that always takes the newest view request (an older one still being
//! rendered is cancelled), so a moving camera never builds a queue of stale frames; saving
//! and rendering camera paths run on blocking threads; training progress is forwarded.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use axum::extract::ws::{Message, WebSocket};
use tokio::sync::{broadcast, mpsc};

use crate::paths;
use crate::protocol::{ClientMessage, ServerMessage};
use crate::render::{encode_levels, level_sizes, render_level, Model, Pacer, ViewRequest};
use crate::state::Viewer;

/// The newest view request, handed from the socket to the render worker.
#[derive(Default)]
struct Latest {
    job: Mutex<Option<ViewRequest>>,
    wake: Condvar,
    /// Counts requests: a render whose generation is no longer current is cancelled.
    generation: AtomicU64,
    closed: AtomicBool,
}

impl Latest {
    fn post(&self, job: ViewRequest) {
        let mut slot = self.job.lock().unwrap_or_else(|e| e.into_inner());
        *slot = Some(job);
        self.generation.fetch_add(1, Ordering::SeqCst);
        self.wake.notify_one();
    }

    fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.generation.fetch_add(1, Ordering::SeqCst);
        let _slot = self.job.lock().unwrap_or_else(|e| e.into_inner());
        self.wake.notify_one();
    }

    /// Waits for the next request; `None` once the page has gone.
    fn take(&self) -> Option<(ViewRequest, u64)> {
        let mut slot = self.job.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if self.closed.load(Ordering::SeqCst) {
                return None;
            }
            if let Some(job) = slot.take() {
                return Some((job, self.generation.load(Ordering::SeqCst)));
            }
            slot = self.wake.wait(slot).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// Renders the newest request, level by level, until the page goes; each level is
/// coloured and encoded on a thread of its own while the next one renders.
fn render_worker(model: Arc<Model>, latest: Arc<Latest>, out: mpsc::UnboundedSender<Message>) {
    // One level waits at most: a slow encoder holds rendering back, not stale frames.
    let (to_encoder, levels) = std::sync::mpsc::sync_channel(1);
    std::thread::scope(|scope| {
        // Dropped when rendering ends, which ends the encoder's loop before the scope
        // waits for it.
        let to_encoder = to_encoder;
        let encoder_model = &model;
        scope.spawn(move || {
            encode_levels(encoder_model, levels, |frame| {
                out.send(Message::Binary(frame.bytes.into())).is_ok()
            })
        });
        let mut pacer = Pacer::default();
        while let Some((job, generation)) = latest.take() {
            let cancelled = || latest.generation.load(Ordering::SeqCst) != generation;
            let preview = pacer.preview_scale(job.camera.width, job.camera.height);
            for size in level_sizes(&job.camera, preview, job.moving) {
                let level = render_level(&model, &mut pacer, &job, size, &cancelled);
                let Some(level) = level else { break };
                if to_encoder.send(level).is_err() {
                    // The encoder stopped: the page has gone.
                    return;
                }
            }
        }
    });
}

fn text(msg: &ServerMessage) -> Message {
    // Serialising these plain structs cannot fail.
    Message::Text(serde_json::to_string(msg).unwrap_or_default().into())
}

fn error(message: impl Into<String>) -> Message {
    text(&ServerMessage::Error {
        message: message.into(),
    })
}

/// Serves one page until it closes its socket.
pub async fn run(viewer: Arc<Viewer>, mut socket: WebSocket) {
    let (tx, mut rx) = mpsc::unbounded_channel::<Message>();
    let latest = Arc::new(Latest::default());
    let worker = {
        let (model, latest, tx) = (viewer.model.clone(), latest.clone(), tx.clone());
        std::thread::spawn(move || render_worker(model, latest, tx))
    };
    let mut training = viewer.training.subscribe();
    viewer.watchers.fetch_add(1, Ordering::SeqCst);
    loop {
        tokio::select! {
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(t))) => handle(&viewer, &latest, &tx, t.as_str()),
                Some(Ok(Message::Binary(_))) => {
                    let _ = tx.send(error("binary messages are not understood; send JSON text"));
                }
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => break,
                Some(Ok(_)) => {}
            },
            outgoing = rx.recv() => match outgoing {
                Some(m) => {
                    if socket.send(m).await.is_err() {
                        break;
                    }
                }
                None => break,
            },
            progress = training.recv() => match progress {
                Ok(m) => {
                    if socket.send(text(&m)).await.is_err() {
                        break;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => {}
            },
        }
    }
    viewer.watchers.fetch_sub(1, Ordering::SeqCst);
    latest.close();
    let _ = tokio::task::spawn_blocking(move || worker.join()).await;
}

/// Acts on one message from the page.
fn handle(
    viewer: &Arc<Viewer>,
    latest: &Latest,
    tx: &mpsc::UnboundedSender<Message>,
    message: &str,
) {
    let msg = match ClientMessage::parse(message) {
        Ok(m) => m,
        Err(e) => {
            let _ = tx.send(error(e.to_string()));
            return;
        }
    };
    match msg {
        ClientMessage::View {
            seq,
            camera,
            mode,
            moving,
            appearance,
            time,
        } => match viewer.appearance(appearance) {
            Ok(appearance) => latest.post(ViewRequest {
                seq,
                camera,
                mode,
                moving,
                appearance,
                time,
            }),
            Err(e) => {
                let _ = tx.send(error(e));
            }
        },
        ClientMessage::PreviewPath { path } => {
            let paths::Frames {
                poses,
                fov_y,
                times,
            } = paths::frames(&path);
            let _ = tx.send(text(&ServerMessage::PathPoses {
                poses,
                fov_y,
                times,
            }));
        }
        ClientMessage::SavePath { name, path } => {
            let (viewer, tx) = (viewer.clone(), tx.clone());
            tokio::task::spawn_blocking(move || {
                let reply = match paths::save(&viewer.run_dir, &name, &path) {
                    Ok(file) => text(&ServerMessage::Saved {
                        file: relative(&viewer, &file),
                    }),
                    Err(e) => error(e),
                };
                let _ = tx.send(reply);
            });
        }
        ClientMessage::RenderPath {
            name,
            path,
            appearance,
        } => {
            let appearance = match viewer.appearance(appearance) {
                Ok(a) => a,
                Err(e) => {
                    let _ = tx.send(error(e));
                    return;
                }
            };
            if viewer.rendering_path.swap(true, Ordering::SeqCst) {
                let _ = tx.send(error("a camera path is already being rendered"));
                return;
            }
            let (viewer, tx) = (viewer.clone(), tx.clone());
            tokio::task::spawn_blocking(move || {
                let progress = |done: usize, total: usize| {
                    let _ = tx.send(text(&ServerMessage::RenderProgress { done, total }));
                };
                let reply = match paths::render(&viewer, &name, &path, appearance, &progress) {
                    Ok(r) => text(&ServerMessage::Rendered {
                        folder: r.folder,
                        video: r.video,
                    }),
                    Err(e) => error(e),
                };
                viewer.rendering_path.store(false, Ordering::SeqCst);
                let _ = tx.send(reply);
            });
        }
    }
}

fn relative(viewer: &Viewer, file: &std::path::Path) -> String {
    file.strip_prefix(&viewer.run_dir)
        .unwrap_or(file)
        .display()
        .to_string()
}
