//! `nerf view`: a trained run in the web browser. A local HTTP server ([`server`]) serves
//! an embedded page (`assets/`: no CDN, no build step) that drives a camera and receives
//! rendered frames over a WebSocket ([`session`], [`protocol`]); frames are rendered
//! progressively and cancelled when the camera moves on ([`render`]); the page's camera-path
//! editor saves nerfstudio `camera_path.json` files and renders them ([`paths`]).
//!
//! Safe by default: the server listens on 127.0.0.1; listening beyond this machine needs
//! `--host` and then a random token in every request. It reads only its run (and the
//! run's scene, through the library) and writes only camera paths and renders inside the
//! run folder, under names it checks.

pub mod bench;
pub mod live;
pub mod paths;
pub mod protocol;
pub mod render;
pub mod server;
pub mod session;
pub mod state;

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;

pub use state::Viewer;

/// The options of `nerf view`.
#[derive(Clone, Debug, clap::Args)]
pub struct ViewOptions {
    /// The run folder to view (what `nerf train --out` wrote).
    #[arg(long)]
    pub run: PathBuf,
    /// Address to listen on. The default serves this machine only; anything else (such
    /// as 0.0.0.0) is reachable from the network and then needs the printed token.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: IpAddr,
    #[arg(long, default_value_t = 7007)]
    pub port: u16,
    /// Open the page in the default web browser.
    #[arg(long)]
    pub open: bool,
    /// Measure instead of serving: frames/s at several sizes, the preview a moving camera
    /// gets, the time to the full frame (seen from the first training camera).
    #[arg(long)]
    pub bench: bool,
    #[command(flatten)]
    pub device: nerf::engine::DeviceArg,
    #[command(flatten)]
    pub scene: nerf::train::run_scene::SceneOverride,
}

/// A random token of 128 bits, in hex.
pub fn random_token() -> anyhow::Result<String> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)
        .map_err(|e| anyhow::anyhow!("no random numbers for the access token: {e}"))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// The token a server on `host` needs: none on loopback addresses, a fresh random one
/// otherwise (with a warning, since the page is then reachable from the network).
pub fn token_for(host: IpAddr) -> anyhow::Result<Option<String>> {
    if host.is_loopback() {
        return Ok(None);
    }
    eprintln!(
        "warning: listening on {host}: anyone who can reach this machine and has the \
         address below (with its token) can view this run and write camera paths into it"
    );
    random_token().map(Some)
}

/// The address to open: the page with its token.
pub fn page_url(addr: SocketAddr, token: Option<&str>) -> String {
    let host = match addr.ip() {
        ip if ip.is_unspecified() => IpAddr::V4(Ipv4Addr::LOCALHOST),
        ip => ip,
    };
    let base = format!("http://{}/", SocketAddr::new(host, addr.port()));
    match token {
        Some(t) => format!("{base}?token={t}"),
        None => base,
    }
}

/// A running server: its address, and a handle that stops it when dropped.
pub struct Running {
    pub addr: SocketAddr,
    pub url: String,
    pub viewer: Arc<Viewer>,
    _runtime: tokio::runtime::Runtime,
}

/// Starts serving `viewer` on `host:port` (port 0: any free port) in a runtime of its own.
pub fn start(viewer: Viewer, host: IpAddr, port: u16) -> anyhow::Result<Running> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("nerf-view")
        .enable_all()
        .build()
        .context("starting the viewer's server runtime")?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind((host, port)))
        .with_context(|| {
            format!("cannot listen on {host}:{port} (is another viewer using it? try --port)")
        })?;
    let addr = listener.local_addr().context("the server's address")?;
    let viewer = Arc::new(viewer);
    let url = page_url(addr, viewer.token.as_deref());
    let app = server::router(viewer.clone());
    runtime.spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            eprintln!("error: the viewer's server stopped: {e}");
        }
    });
    Ok(Running {
        addr,
        url,
        viewer,
        _runtime: runtime,
    })
}

/// Opens `url` in the desktop's browser (best effort: says so when it cannot).
pub fn open_browser(url: &str) {
    let opener = if cfg!(target_os = "macos") {
        "open"
    } else if cfg!(target_os = "windows") {
        "explorer"
    } else {
        "xdg-open"
    };
    if let Err(e) = std::process::Command::new(opener).arg(url).spawn() {
        eprintln!("note: could not open a browser ({opener}: {e}); open {url} yourself");
    }
}

/// `nerf view`: serves the run until interrupted.
pub fn run(opts: &ViewOptions) -> anyhow::Result<()> {
    let run = nerf::train::folder::LoadedRun::open_with(&opts.run, opts.device.device, &opts.scene)
        .with_context(|| format!("opening the run {}", opts.run.display()))?;
    if let Some(note) = nerf::train::run_scene::missing_note(&run.config) {
        eprintln!("note: {note}");
    }
    eprintln!(
        "viewing {} (step {}, {})",
        opts.run.display(),
        run.step,
        run.engine.describe()
    );
    if opts.bench {
        let scene = run.config.open_scene(1)?;
        let settings =
            nerf::views::RenderSettings::of_scene(&scene, run.config.background.eval_colour());
        let camera = scene
            .cameras(nerf::data::Split::Train)
            .first()
            .cloned()
            .context("the run's scene has no training cameras to look from")?;
        let fov_y = camera.fov_y_degrees();
        let model = render::Model {
            run: std::sync::RwLock::new(run),
            settings,
            camera_distance: nerf::math::length(camera.origin()),
            pool: None,
        };
        let report = bench::run(&model, camera.c2w, fov_y, &[150, 300, 600], (800, 600));
        report.print();
        return Ok(());
    }
    let token = token_for(opts.host)?;
    let viewer = Viewer::new(run, opts.run.clone(), token, false)?;
    let running = start(viewer, opts.host, opts.port)?;
    println!("viewer at {}", running.url);
    if opts.open {
        open_browser(&running.url);
    }
    eprintln!("press Ctrl-C to stop");
    loop {
        std::thread::park();
    }
}
