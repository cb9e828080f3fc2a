//! The viewer's server end to end on a small trained run: the page and API over HTTP, the
//! WebSocket protocol (frames that match `nerf render`'s pixels, progressive refinement,
//! malformed messages, path-traversal names), the token when listening beyond loopback,
//! and saved camera paths that `nerf render --path file` renders.

use std::io::{Read, Write};
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpStream};
use std::path::Path;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use nerf::engine::Device;
use nerf::train::folder::LoadedRun;
use nerf_view::protocol::{FrameHeader, ServerMessage, HEADER_BYTES};
use nerf_view::{start, Running, Viewer};
use tokio_tungstenite::tungstenite::Message;

use crate::common::{trained_run, LOUD_PHOTO, TRAINED_STEPS};

const LOCAL: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

fn serve(run: &Path, host: IpAddr, token: Option<String>) -> Running {
    let loaded = LoadedRun::open_on(run, Device::Cpu).expect("open run");
    let viewer = Viewer::new(loaded, run.to_path_buf(), token, false).expect("viewer");
    start(viewer, host, 0).expect("start")
}

/// A plain HTTP/1.1 GET: status code and body.
fn get(addr: SocketAddr, path: &str) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(60)))
        .expect("timeout");
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .expect("send");
    let mut all = Vec::new();
    s.read_to_end(&mut all).expect("read");
    let end = all
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("headers");
    let head = String::from_utf8_lossy(&all[..end]).to_string();
    let status = head[9..12].parse().expect("status");
    let body = all[end + 4..].to_vec();
    // Bodies here are small; a chunked body's framing is stripped well enough by
    // taking what is between the first chunk size line and the final zero chunk.
    if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        return (status, dechunk(&body));
    }
    (status, body)
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let Some(line) = b.windows(2).position(|w| w == b"\r\n") else {
            return out;
        };
        let size =
            usize::from_str_radix(String::from_utf8_lossy(&b[..line]).trim(), 16).unwrap_or(0);
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[line + 2..line + 2 + size]);
        b = &b[line + 2 + size + 2..];
    }
}

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn next(ws: &mut Socket) -> Message {
    tokio::time::timeout(Duration::from_secs(120), ws.next())
        .await
        .expect("an answer within two minutes")
        .expect("open")
        .expect("a message")
}

/// The next text message, as a server message (frames before it are skipped).
async fn next_text(ws: &mut Socket) -> ServerMessage {
    loop {
        if let Message::Text(t) = next(ws).await {
            return serde_json::from_str(t.as_str()).expect("a server message");
        }
    }
}

fn view_request(
    seq: u32,
    c2w: [[f32; 4]; 3],
    fov_y: f32,
    size: (usize, usize),
    mode: &str,
) -> String {
    serde_json::json!({
        "type": "view", "seq": seq, "mode": mode, "moving": false,
        "camera": {"c2w": c2w, "fov_y": fov_y, "width": size.0, "height": size.1}
    })
    .to_string()
}

#[test]
fn the_viewer_serves_its_run_and_only_its_run() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run_dir = trained_run(dir.path());
    let server = serve(&run_dir, LOCAL, None);
    let addr = server.addr;

    // The page, its script and the scene description.
    let (status, page) = get(addr, "/");
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&page).contains("viewer.js"));
    let (status, js) = get(addr, "/viewer.js");
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&js).contains("new WebSocket"));
    let (status, scene) = get(addr, "/api/scene");
    assert_eq!(status, 200);
    let scene: serde_json::Value = serde_json::from_slice(&scene).expect("json");
    assert_eq!(scene["cameras"].as_array().map(Vec::len), Some(12));
    assert_eq!(scene["step"], TRAINED_STEPS);
    assert_eq!(scene["appearance_photos"], 12);
    // A training photo by index, and clear refusals for anything else.
    let (status, jpeg) = get(addr, "/api/photo/2");
    assert_eq!(status, 200);
    assert_eq!(&jpeg[..2], &[0xff, 0xd8], "a JPEG");
    let (status, body) = get(addr, "/api/photo/12");
    assert_eq!(status, 404);
    assert!(String::from_utf8_lossy(&body).contains("no training photo 12"));
    let (status, _) = get(addr, "/api/photo/..%2F..%2Fconfig.json");
    assert_eq!(status, 400);
    for path in [
        "/../config.json",
        "/config.json",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/assets/viewer.js",
    ] {
        assert_eq!(get(addr, path).0, 404, "{path}");
    }

    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
            .await
            .expect("websocket");
        // Malformed messages: an error each, and the connection keeps serving.
        for bad in [
            "{not json".to_string(),
            r#"{"type":"view","seq":1}"#.to_string(),
            r#"{"type":"view","seq":1,"mode":"rgb","appearance":12,"camera":{"c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,4]],"fov_y":40,"width":8,"height":8}}"#.to_string(),
            view_request(1, [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0]], 40.0, (9000, 10), "rgb"),
            r#"{"type":"save_path","name":"../../escape","path":{"keyframes":[{"c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,4]],"fov_y":40},{"c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,3]],"fov_y":40}],"seconds":1,"fps":4,"width":16,"height":16}}"#.to_string(),
        ] {
            ws.send(Message::text(bad.clone())).await.expect("send");
            match next_text(&mut ws).await {
                ServerMessage::Error { message } => eprintln!("refused as expected: {message}"),
                other => panic!("{bad}: {other:?}"),
            }
        }
        ws.send(Message::binary(vec![1u8, 2, 3])).await.expect("send");
        assert!(matches!(next_text(&mut ws).await, ServerMessage::Error { .. }));
        assert!(!dir.path().join("escape.json").exists());

        // A view: frames at growing sizes up to the full one, the last one close to the
        // same camera rendered by `nerf render`'s code.
        let test_cam = {
            let run = LoadedRun::open(&run_dir).expect("run");
            run.config.open_scene(1).expect("scene").cameras(nerf::data::Split::Test)[0].clone()
        };
        let fov_y = test_cam.fov_y_degrees();
        let size = (test_cam.width, test_cam.height);
        ws.send(Message::text(view_request(7, test_cam.c2w, fov_y, size, "rgb")))
            .await
            .expect("send");
        let mut widths = Vec::new();
        let last = loop {
            if let Message::Binary(b) = next(&mut ws).await {
                let h = FrameHeader::decode(&b).expect("header");
                assert_eq!(h.seq, 7);
                widths.push(h.width);
                if h.last {
                    break b;
                }
            }
        };
        assert_eq!(*widths.last().expect("frames") as usize, size.0);
        assert!(widths.windows(2).all(|w| w[0] < w[1]), "growing sizes {widths:?}");
        let got = image::load_from_memory(&last[HEADER_BYTES..]).expect("jpeg").to_rgb8();
        let want = {
            let run = LoadedRun::open(&run_dir).expect("run");
            let scene = run.config.open_scene(1).expect("scene");
            let settings = nerf::views::RenderSettings::of_scene(&scene, run.config.background.eval_colour());
            nerf::views::render_view(run.engine.as_ref(), &test_cam, &settings, &|_| {})
        };
        let mse: f64 = got
            .as_raw()
            .iter()
            .zip(&want.rgb)
            .map(|(&a, &b)| (a as f64 / 255.0 - b.clamp(0.0, 1.0) as f64).powi(2))
            .sum::<f64>()
            / want.rgb.len() as f64;
        let psnr = -10.0 * mse.log10();
        eprintln!("viewer frame against nerf render: {psnr:.1} dB (JPEG)");
        assert!(psnr > 35.0, "the frame is not the render: {psnr:.1} dB");

        // The same view with one training photo's learned look, as `nerf
        // render --appearance-of` renders it, and unlike the mean look.
        let mut request: serde_json::Value =
            serde_json::from_str(&view_request(9, test_cam.c2w, fov_y, size, "rgb")).expect("json");
        request["appearance"] = serde_json::json!(LOUD_PHOTO);
        ws.send(Message::text(request.to_string())).await.expect("send");
        let looked = loop {
            if let Message::Binary(b) = next(&mut ws).await {
                let h = FrameHeader::decode(&b).expect("header");
                if h.last && h.seq == 9 {
                    break b;
                }
            }
        };
        let looked = image::load_from_memory(&looked[HEADER_BYTES..]).expect("jpeg").to_rgb8();
        let want_look = {
            let run = LoadedRun::open(&run_dir).expect("run");
            let scene = run.config.open_scene(1).expect("scene");
            let settings = nerf::views::RenderSettings {
                appearance: nerf::stage::Appearance::Of(LOUD_PHOTO as u32),
                ..nerf::views::RenderSettings::of_scene(&scene, run.config.background.eval_colour())
            };
            nerf::views::render_view(run.engine.as_ref(), &test_cam, &settings, &|_| {})
        };
        let psnr_of = |a: &[u8], b: &[f32]| {
            let mse = a
                .iter()
                .zip(b)
                .map(|(&a, &b)| (a as f64 / 255.0 - b.clamp(0.0, 1.0) as f64).powi(2))
                .sum::<f64>()
                / b.len() as f64;
            -10.0 * mse.log10()
        };
        let (same, mean) = (psnr_of(looked.as_raw(), &want_look.rgb), psnr_of(looked.as_raw(), &want.rgb));
        eprintln!("photo {LOUD_PHOTO}'s look: {same:.1} dB against its render, {mean:.1} dB against the mean look");
        assert!(same > 35.0 && mean < same - 5.0, "{same:.1} dB / {mean:.1} dB");

        // Depth and opacity frames come too.
        for mode in ["depth", "opacity"] {
            ws.send(Message::text(view_request(8, test_cam.c2w, fov_y, (24, 24), mode)))
                .await
                .expect("send");
            loop {
                if let Message::Binary(b) = next(&mut ws).await {
                    let h = FrameHeader::decode(&b).expect("header");
                    if h.last && h.seq == 8 {
                        break;
                    }
                }
            }
        }

        // A camera path: previewed, saved (and rendered by `nerf render --path file`).
        let keys = serde_json::json!([
            {"c2w": nerf::camera::look_at([4.0, 0.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]), "fov_y": 40},
            {"c2w": nerf::camera::look_at([0.0, 4.0, 1.5], [0.0; 3], [0.0, 0.0, 1.0]), "fov_y": 45},
        ]);
        let path = serde_json::json!({"keyframes": keys, "seconds": 1, "fps": 3, "width": 20, "height": 16});
        ws.send(Message::text(serde_json::json!({"type": "preview_path", "path": path}).to_string()))
            .await
            .expect("send");
        match next_text(&mut ws).await {
            ServerMessage::PathPoses { poses, fov_y, times } => {
                assert_eq!((poses.len(), fov_y.len()), (3, 3));
                assert_eq!(times, None, "keyframes without time");
            }
            other => panic!("{other:?}"),
        }
        ws.send(Message::text(
            serde_json::json!({"type": "save_path", "name": "take_1", "path": path}).to_string(),
        ))
        .await
        .expect("send");
        match next_text(&mut ws).await {
            ServerMessage::Saved { file } => assert_eq!(file, "camera_paths/take_1.json"),
            other => panic!("{other:?}"),
        }
        // "Render video": the same code as `nerf render --path file`, with progress.
        ws.send(Message::text(
            serde_json::json!({"type": "render_path", "name": "take_1", "path": path}).to_string(),
        ))
        .await
        .expect("send");
        let mut progress = Vec::new();
        loop {
            match next_text(&mut ws).await {
                ServerMessage::RenderProgress { done, total } => progress.push((done, total)),
                ServerMessage::Rendered { folder, video } => {
                    assert_eq!(folder, "renders/take_1");
                    let video = video.expect("a video");
                    assert!(run_dir.join(&video).exists(), "{video}");
                    break;
                }
                other => panic!("{other:?}"),
            }
        }
        assert!(!progress.is_empty() && progress.iter().all(|&(_, t)| t == 3), "{progress:?}");
        assert!(run_dir.join("renders/take_1/frame_0002.png").exists());
        let _ = ws.close(None).await;
    });
    let saved = run_dir.join("camera_paths/take_1.json");
    let cameras = nerf::camera::path::load_camera_path(&saved, None).expect("a camera path");
    assert_eq!(cameras.len(), 3);
    assert_eq!((cameras[0].width, cameras[0].height), (20, 16));
}

/// Beyond loopback the page, the API and the socket need the token.
#[test]
fn listening_beyond_this_machine_needs_the_token() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run_dir = trained_run(dir.path());
    let token = nerf_view::token_for(IpAddr::V4(Ipv4Addr::UNSPECIFIED))
        .expect("token")
        .expect("a token off loopback");
    assert_eq!(token.len(), 32);
    assert_eq!(nerf_view::token_for(LOCAL).expect("token"), None);
    let server = serve(
        &run_dir,
        IpAddr::V4(Ipv4Addr::UNSPECIFIED),
        Some(token.clone()),
    );
    let addr = SocketAddr::new(LOCAL, server.addr.port());
    assert!(
        server.url.ends_with(&format!("?token={token}")),
        "{}",
        server.url
    );
    for path in ["/", "/api/scene", "/api/photo/0", "/ws"] {
        let (status, body) = get(addr, path);
        assert_eq!(status, 403, "{path}");
        assert!(String::from_utf8_lossy(&body).contains("token"));
        assert_eq!(get(addr, &format!("{path}?token=wrong")).0, 403, "{path}");
    }
    assert_eq!(get(addr, &format!("/?token={token}")).0, 200);
    assert_eq!(get(addr, &format!("/api/scene?token={token}")).0, 200);
}
