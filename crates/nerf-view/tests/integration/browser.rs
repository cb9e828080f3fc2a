//! The viewer in a real browser: headless Chromium driven over WebDriver (chromedriver)
//! loads the page of a small trained run, and the test checks that a frame is drawn and
//! matches `nerf render`'s pixels for the page's camera, that a mouse drag moves the view,
//! and that two keyframes saved from the path editor make a `camera_path.json` that renders
//! through `nerf render --path file`'s code. Skips with a message where Chromium or
//! chromedriver is missing. `NERF_VIEW_SCREENSHOTS=DIR` also saves the page's screenshots.

use std::io::{Read, Write};
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use nerf::app::frames::{render_frames, FramesOptions, PathKind};
use nerf::engine::Device;
use nerf::train::folder::LoadedRun;
use nerf_view::protocol::ViewCamera;
use nerf_view::render::camera_at;
use serde_json::{json, Value};

use crate::common::{trained_run, LOUD_PHOTO};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// One request to chromedriver: method, path, JSON body; the answer's `value`.
fn call(addr: SocketAddr, method: &str, path: &str, body: Option<&Value>) -> Value {
    let body = body.map(Value::to_string).unwrap_or_default();
    let mut s = TcpStream::connect(addr).expect("chromedriver");
    s.set_read_timeout(Some(Duration::from_secs(120)))
        .expect("timeout");
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .expect("send");
    // chromedriver keeps the connection open: read the headers, then Content-Length bytes.
    let mut all = Vec::new();
    let mut buf = [0u8; 65536];
    let end = loop {
        let n = s.read(&mut buf).expect("read");
        assert!(n > 0, "chromedriver closed the connection");
        all.extend_from_slice(&buf[..n]);
        if let Some(end) = all.windows(4).position(|w| w == b"\r\n\r\n") {
            break end;
        }
    };
    let head = String::from_utf8_lossy(&all[..end]).to_ascii_lowercase();
    let length: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .and_then(|v| v.trim().parse().ok())
        .expect("a content length");
    while all.len() < end + 4 + length {
        let n = s.read(&mut buf).expect("read");
        assert!(n > 0, "chromedriver closed the connection early");
        all.extend_from_slice(&buf[..n]);
    }
    let v: Value = serde_json::from_slice(&all[end + 4..end + 4 + length]).expect("json");
    if let Some(e) = v["value"].get("error") {
        panic!("webdriver {method} {path}: {e}: {}", v["value"]["message"]);
    }
    v["value"].clone()
}

/// A headless Chromium session; quits (and stops chromedriver) when dropped.
struct Browser {
    driver: Child,
    addr: SocketAddr,
    session: String,
}

impl Browser {
    fn start() -> Option<Browser> {
        for exe in [CHROMIUM, CHROMEDRIVER] {
            if !Path::new(exe).exists() {
                eprintln!("skipping the browser test: {exe} is missing (apt-get install chromium chromium-driver)");
                return None;
            }
        }
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let driver = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let addr = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), port);
        let t0 = Instant::now();
        while TcpStream::connect(addr).is_err() {
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "chromedriver did not start"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": CHROMIUM, "args": [
                "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--window-size=1100,760",
                "--disable-dev-shm-usage"
            ]}
        }}});
        let v = call(addr, "POST", "/session", Some(&caps));
        let session = v["sessionId"].as_str().expect("session").to_string();
        Some(Browser {
            driver,
            addr,
            session,
        })
    }

    fn cmd(&self, method: &str, what: &str, body: Option<Value>) -> Value {
        let path = format!("/session/{}/{what}", self.session);
        call(self.addr, method, &path, body.as_ref())
    }

    fn goto(&self, url: &str) {
        self.cmd("POST", "url", Some(json!({ "url": url })));
    }

    /// Runs `script` (a function body) in the page.
    fn js(&self, script: &str) -> Value {
        self.cmd(
            "POST",
            "execute/sync",
            Some(json!({"script": script, "args": []})),
        )
    }

    fn wait_for(&self, what: &str, script: &str) -> Value {
        let t0 = Instant::now();
        loop {
            let v = self.js(script);
            if !v.is_null() && v != json!(false) {
                return v;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(180),
                "timed out waiting for {what}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn click(&self, id: &str) {
        self.js(&format!(
            "document.getElementById({id:?}).click(); return true;"
        ));
    }

    /// A real mouse drag from (x, y) by (dx, dy), in viewport pixels.
    fn drag(&self, (x, y): (i64, i64), (dx, dy): (i64, i64)) {
        let actions = json!({"actions": [{"type": "pointer", "id": "mouse",
        "parameters": {"pointerType": "mouse"}, "actions": [
            {"type": "pointerMove", "x": x, "y": y, "origin": "viewport"},
            {"type": "pointerDown", "button": 0},
            {"type": "pointerMove", "x": x + dx / 2, "y": y + dy / 2, "duration": 100, "origin": "viewport"},
            {"type": "pointerMove", "x": x + dx, "y": y + dy, "duration": 100, "origin": "viewport"},
            {"type": "pointerUp", "button": 0}
        ]}]});
        self.cmd("POST", "actions", Some(actions));
    }

    fn screenshot(&self, name: &str) {
        let Some(dir) = std::env::var_os("NERF_VIEW_SCREENSHOTS") else {
            return;
        };
        let png = self.cmd("GET", "screenshot", None);
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(png.as_str().expect("base64"))
            .expect("png");
        std::fs::write(PathBuf::from(dir).join(name), bytes).expect("write screenshot");
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let path = format!("/session/{}", self.session);
        let _ = std::panic::catch_unwind(|| call(self.addr, "DELETE", &path, None));
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

/// The drawn frame once the final one for the current camera is in: its sequence number,
/// width, height and RGBA pixels.
const FINAL_FRAME: &str = r#"
    const c = document.getElementById("frame");
    if (c.dataset.last !== "true" || Number(c.dataset.seq) !== seq) return null;
    const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    return [Number(c.dataset.seq), c.width, c.height, Array.from(d)];
"#;

fn final_frame(b: &Browser, what: &str) -> (u64, usize, usize, Vec<u8>) {
    let v = b.wait_for(what, FINAL_FRAME);
    let px: Vec<u8> = v[3]
        .as_array()
        .expect("pixels")
        .iter()
        .map(|p| p.as_u64().unwrap_or(0) as u8)
        .collect();
    (
        v[0].as_u64().unwrap_or(0),
        v[1].as_u64().unwrap_or(0) as usize,
        v[2].as_u64().unwrap_or(0) as usize,
        px,
    )
}

/// The page's camera, as it sent it.
fn page_camera(b: &Browser) -> ViewCamera {
    let v = b.js(
        "const [w, h] = renderSize(); return {c2w: pose(), fov_y: view.fov, width: w, height: h};",
    );
    serde_json::from_value(v).expect("camera")
}

#[test]
fn the_page_draws_the_model_follows_the_mouse_and_saves_paths() {
    let Some(browser) = Browser::start() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let run_dir = trained_run(dir.path());
    let loaded = LoadedRun::open_on(&run_dir, Device::Cpu).expect("run");
    let viewer = nerf_view::Viewer::new(loaded, run_dir.clone(), None, false).expect("viewer");
    let server = nerf_view::start(viewer, IpAddr::V4(Ipv4Addr::LOCALHOST), 0).expect("server");
    browser.goto(&server.url);
    // A small render size keeps the test quick on two cores.
    browser.wait_for(
        "the scene",
        "return typeof scene !== 'undefined' && scene !== null;",
    );
    browser.js("const r = document.getElementById('resolution'); r.value = '320'; r.dispatchEvent(new Event('change')); return true;");
    browser.wait_for("two view requests", "return seq >= 2;");

    // A frame is drawn, not blank, and it is the model's render of the page's camera.
    let (seq, w, h, px) = final_frame(&browser, "the first full frame");
    let camera = page_camera(&browser);
    assert_eq!((w, h), (camera.width, camera.height));
    let run = LoadedRun::open(&run_dir).expect("run");
    let scene = run.config.open_scene(1).expect("scene");
    let settings =
        nerf::views::RenderSettings::of_scene(&scene, run.config.background.eval_colour());
    let want = nerf::views::render_view(
        run.engine.as_ref(),
        &camera_at(&camera, w, h),
        &settings,
        &|_| {},
    );
    let rgb: Vec<f32> = px
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .map(|v| v as f32 / 255.0)
        .collect();
    let mean = rgb.iter().sum::<f32>() / rgb.len() as f32;
    let spread = rgb.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / rgb.len() as f32;
    assert!(spread > 1e-3, "the frame is blank (variance {spread})");
    let mse = rgb
        .iter()
        .zip(&want.rgb)
        .map(|(a, b)| (a - b.clamp(0.0, 1.0)).powi(2) as f64)
        .sum::<f64>()
        / rgb.len() as f64;
    let psnr = -10.0 * mse.log10();
    eprintln!("page frame {w}x{h} against nerf render: {psnr:.1} dB");
    assert!(psnr > 30.0, "the page shows something else: {psnr:.1} dB");
    browser.screenshot("view.png");

    // The look of one training photo, picked on the page, is what `nerf
    // render --appearance-of` renders.
    let shown = browser.js("return !document.getElementById('appearance-box').hidden;");
    assert_eq!(shown, json!(true), "the look picker is hidden");
    browser.js(&format!(
        "const a = document.getElementById('appearance'); a.value = '{LOUD_PHOTO}'; \
         a.dispatchEvent(new Event('change')); return true;"
    ));
    let (_, _, _, looked) = final_frame(&browser, "the frame with a photo's look");
    let look_settings = nerf::views::RenderSettings {
        appearance: nerf::stage::Appearance::Of(LOUD_PHOTO as u32),
        ..settings
    };
    let want_look = nerf::views::render_view(
        run.engine.as_ref(),
        &camera_at(&camera, w, h),
        &look_settings,
        &|_| {},
    );
    let psnr_to = |px: &[u8], want: &[f32]| {
        let mse = px
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .zip(want)
            .map(|(a, b)| (a as f64 / 255.0 - b.clamp(0.0, 1.0) as f64).powi(2))
            .sum::<f64>()
            / want.len() as f64;
        -10.0 * mse.log10()
    };
    let (same, mean_look) = (
        psnr_to(&looked, &want_look.rgb),
        psnr_to(&looked, &want.rgb),
    );
    eprintln!("photo {LOUD_PHOTO}'s look on the page: {same:.1} dB against its render, {mean_look:.1} dB against the mean look");
    assert!(
        same > 30.0 && mean_look < same - 5.0,
        "{same:.1} / {mean_look:.1} dB"
    );
    browser.screenshot("look.png");
    browser.js("const a = document.getElementById('appearance'); a.value = ''; a.dispatchEvent(new Event('change')); return true;");
    let (_, _, _, at_start) = final_frame(&browser, "the frame with the mean look again");

    // The turning chair at its last moment, picked with the time slider, is what `nerf
    // render --time 1` renders.
    let shown = browser.js("return !document.getElementById('time-box').hidden;");
    assert_eq!(shown, json!(true), "the time slider is hidden");
    browser.js("const t = document.getElementById('time'); t.value = '1'; \
         t.dispatchEvent(new Event('input')); return true;");
    browser.wait_for("the request at the last moment", "return time === 1;");
    let (_, _, _, last) = final_frame(&browser, "the frame at the last moment");
    let at_end = nerf::views::RenderSettings {
        time: Some(1.0),
        ..settings
    };
    let want_end = nerf::views::render_view(
        run.engine.as_ref(),
        &camera_at(&camera, w, h),
        &at_end,
        &|_| {},
    );
    let (same, first) = (
        psnr_to(&last, &want_end.rgb),
        psnr_to(&at_start, &want_end.rgb),
    );
    eprintln!("the last moment on the page: {same:.1} dB against its render, the first moment {first:.1} dB against it");
    assert!(
        same > 30.0 && first < same - 3.0,
        "{same:.1} / {first:.1} dB"
    );
    browser.screenshot("time.png");
    browser.js("const t = document.getElementById('time'); t.value = '0'; \
         t.dispatchEvent(new Event('input')); return true;");

    // A drag orbits the camera: a new frame for a new view.
    browser.js("document.getElementById('key-add').click(); return true;");
    let before = page_camera(&browser);
    browser.drag((300, 300), (120, 40));
    browser.wait_for("a new request", &format!("return seq > {seq};"));
    let after = page_camera(&browser);
    assert_ne!(before.c2w, after.c2w, "the drag did not move the camera");
    let (_, _, _, moved) = final_frame(&browser, "the frame after the drag");
    assert_ne!(moved, px, "the picture did not change");

    // Two keyframes, saved from the editor, render through `nerf render --path file`; the
    // second keeps the last moment, so time runs from 0 to 1 along the path.
    browser.js("const t = document.getElementById('time'); t.value = '1'; \
         t.dispatchEvent(new Event('input')); return true;");
    browser.click("key-add");
    browser.js(
        "document.getElementById('path-name').value = 'browser_take'; \
         document.getElementById('seconds').value = '1'; \
         const fps = document.getElementById('fps'); fps.value = '4'; \
         fps.dispatchEvent(new Event('change')); return true;",
    );
    browser.wait_for("the path preview", "return pathPoses !== null;");
    browser.screenshot("path_editor.png");
    browser.click("save");
    let status = browser.wait_for(
        "the saved path",
        "const s = document.getElementById('path-status').textContent; return s.startsWith('saved') ? s : null;",
    );
    assert_eq!(status, json!("saved camera_paths/browser_take.json"));
    let file = run_dir.join("camera_paths/browser_take.json");
    let times = nerf::camera::path::load_camera_path_times(&file).expect("times");
    let expected = [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0];
    assert!(
        times.len() == 4
            && times
                .iter()
                .zip(expected)
                .all(|(t, e)| t.is_some_and(|t| (t - e).abs() < 1e-5)),
        "the saved path's moments: {times:?}"
    );
    // Scrubbing the preview shows each frame at its moment.
    let scrubbed = browser.js(
        "const s = document.getElementById('scrub'); s.value = '2'; \
         s.dispatchEvent(new Event('input')); return time;",
    );
    assert!(
        scrubbed
            .as_f64()
            .is_some_and(|t| (t - 2.0 / 3.0).abs() < 1e-5),
        "scrubbed to frame 2: time {scrubbed}"
    );
    let mut opts = FramesOptions::orbit(2, 1.0, dir.path().join("take.gif"));
    opts.path = PathKind::File;
    opts.camera_path = Some(file);
    opts.size = Some(24);
    let report = render_frames(&run, &opts, &dir.path().join("frames"), &|_| {}).expect("render");
    assert_eq!(report.frames, 4, "1 s at 4 frames a second");
    assert!(dir.path().join("frames/frame_0003.png").exists());
    drop(server);
}
