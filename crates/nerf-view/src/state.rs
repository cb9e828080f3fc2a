//! What one viewer serves: the run (model, scene, training cameras), its folder, the
//! access token, and the channel that carries training progress to every open page.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock, RwLock};

use nerf::camera::Camera;
use nerf::data::image::to_u8;
use nerf::data::scene::Scene;
use nerf::data::{Dataset, Split};
use nerf::engine::EngineState;
use nerf::train::folder::LoadedRun;
use nerf::views::RenderSettings;
use serde::Serialize;
use tokio::sync::broadcast;

use crate::protocol::ServerMessage;
use crate::render::Model;

/// A training camera as the page draws it.
#[derive(Clone, Debug, Serialize)]
pub struct CameraInfo {
    pub index: usize,
    pub c2w: [[f32; 4]; 3],
    /// Vertical field of view in degrees.
    pub fov_y: f32,
    pub width: usize,
    pub height: usize,
}

/// What the page needs to set itself up (`/api/scene`).
#[derive(Clone, Debug, Serialize)]
pub struct SceneInfo {
    pub run: String,
    pub step: u64,
    pub engine: String,
    pub cameras: Vec<CameraInfo>,
    /// The average camera "up" (the page orbits about it), the point the cameras look at
    /// (the orbit's centre) and their mean distance from it.
    pub up: [f32; 3],
    pub center: [f32; 3],
    pub radius: f32,
    /// Whether a run is training under this viewer (progress messages will come).
    pub live: bool,
    /// Training photos with a learned appearance code (`--appearance`; 0 without): the
    /// page offers to render with any one's look.
    pub appearance_photos: usize,
    /// A model of a moving scene: the page shows a time slider and a play button.
    pub dynamic: bool,
}

/// One viewer's shared state.
pub struct Viewer {
    pub model: Arc<Model>,
    pub run_dir: PathBuf,
    pub scene: Scene,
    pub info: SceneInfo,
    /// Required in every request's `token` query parameter when set (the server listens
    /// beyond this machine).
    pub token: Option<String>,
    /// Training progress for open pages (`nerf train --view`).
    pub training: broadcast::Sender<ServerMessage>,
    /// The training photos, loaded on the first request for one.
    photos: OnceLock<std::result::Result<Dataset, String>>,
    /// A camera path is being rendered (one at a time).
    pub rendering_path: AtomicBool,
    /// Pages connected now.
    pub watchers: AtomicUsize,
}

impl Viewer {
    /// A viewer of `run` (trained in `run_dir`); `live` when a run trains under it.
    pub fn new(
        run: LoadedRun,
        run_dir: PathBuf,
        token: Option<String>,
        live: bool,
    ) -> nerf::error::Result<Viewer> {
        let scene = run.config.open_scene(1)?;
        let settings = RenderSettings::of_scene(&scene, run.config.background.eval_colour());
        let cameras = scene.cameras(Split::Train);
        let info = SceneInfo {
            run: run_dir.display().to_string(),
            step: run.step,
            engine: run.engine.describe(),
            cameras: cameras.iter().enumerate().map(camera_info).collect(),
            up: mean_up(&cameras),
            center: [0.0; 3],
            radius: mean_distance(&cameras, [0.0; 3]),
            live,
            appearance_photos: run.config.model.appearance_photos(),
            dynamic: run.config.model.is_dynamic(),
        };
        Ok(Viewer {
            model: Arc::new(Model {
                run: RwLock::new(run),
                settings,
                camera_distance: info.radius,
                // Beside a training run the viewer renders on half the cores.
                pool: live
                    .then(|| {
                        let threads = (rayon::current_num_threads() / 2).max(1);
                        rayon::ThreadPoolBuilder::new()
                            .num_threads(threads)
                            .thread_name(|i| format!("nerf-view-{i}"))
                            .build()
                            .ok()
                    })
                    .flatten(),
            }),
            run_dir,
            scene,
            info,
            token,
            training: broadcast::channel(64).0,
            photos: OnceLock::new(),
            rendering_path: AtomicBool::new(false),
            watchers: AtomicUsize::new(0),
        })
    }

    /// Whether any page is open.
    pub fn watched(&self) -> bool {
        self.watchers.load(Ordering::SeqCst) > 0
    }

    /// Shows the weights of training step `step` from now on.
    pub fn update(&self, step: u64, state: EngineState) -> nerf::error::Result<()> {
        let mut run = self.model.run.write().unwrap_or_else(|e| e.into_inner());
        run.engine.set_state(state)?;
        run.step = step;
        Ok(())
    }

    /// Training photo `index` as a JPEG (composited over the run's background).
    pub fn photo(&self, index: usize) -> std::result::Result<Vec<u8>, String> {
        let data = self
            .photos
            .get_or_init(|| self.scene.load(Split::Train, 1).map_err(|e| e.to_string()))
            .as_ref()
            .map_err(Clone::clone)?;
        let view = data
            .views
            .get(index)
            .ok_or_else(|| format!("no training photo {index} (there are {})", data.views.len()))?;
        let rgb = view.image.composite(self.model.settings.background);
        let bytes: Vec<u8> = rgb.iter().map(|&v| to_u8(v)).collect();
        Ok(crate::render::jpeg(
            &bytes,
            view.image.width,
            view.image.height,
        ))
    }
}

impl Viewer {
    /// The render settings' appearance for a page's choice, or why it cannot be.
    pub fn appearance(
        &self,
        photo: Option<u32>,
    ) -> std::result::Result<nerf::stage::Appearance, String> {
        let Some(i) = photo else {
            return Ok(nerf::stage::Appearance::Mean);
        };
        let n = self.info.appearance_photos;
        if n == 0 {
            return Err(
                "this run has no per-photo appearance (train with --appearance)".to_string(),
            );
        }
        if i as usize >= n {
            return Err(format!(
                "appearance of photo {i}: the run has codes for photos 0 to {}",
                n - 1
            ));
        }
        Ok(nerf::stage::Appearance::Of(i))
    }
}

fn camera_info((index, c): (usize, &Camera)) -> CameraInfo {
    CameraInfo {
        index,
        c2w: c.c2w,
        fov_y: c.fov_y_degrees(),
        width: c.width,
        height: c.height,
    }
}

/// The cameras' mean "up" axis (their y columns), or +z without cameras.
fn mean_up(cameras: &[Camera]) -> [f32; 3] {
    let mut up = [0.0f32; 3];
    for c in cameras {
        for (r, u) in up.iter_mut().enumerate() {
            *u += c.c2w[r][1];
        }
    }
    let len = up.iter().map(|v| v * v).sum::<f32>().sqrt();
    if len > 1e-6 {
        up.map(|v| v / len)
    } else {
        [0.0, 0.0, 1.0]
    }
}

fn mean_distance(cameras: &[Camera], center: [f32; 3]) -> f32 {
    if cameras.is_empty() {
        return 4.0;
    }
    let sum: f32 = cameras
        .iter()
        .map(|c| {
            let o = c.origin();
            ((o[0] - center[0]).powi(2) + (o[1] - center[1]).powi(2) + (o[2] - center[2]).powi(2))
                .sqrt()
        })
        .sum();
    sum / cameras.len() as f32
}
