//! What the page and the server say to each other over the WebSocket.
//!
//! The page sends JSON text messages ([`ClientMessage`]); the server answers with JSON text
//! ([`ServerMessage`]) and with rendered frames as binary messages: a 16-byte header
//! ([`FrameHeader`]) followed by a JPEG. Every field the page sends is checked here
//! ([`ClientMessage::parse`]): a malformed or out-of-range message is answered with an
//! error message and the connection stays open.

use serde::{Deserialize, Serialize};

/// Largest rendered image side, and most pixels in one frame.
pub const MAX_SIDE: usize = 4096;
pub const MAX_PIXELS: usize = 1 << 24;
/// Most keyframes of a camera path, and the longest path (seconds) and highest rate.
pub const MAX_KEYFRAMES: usize = 1000;
pub const MAX_SECONDS: f32 = 3600.0;
pub const MAX_FPS: f32 = 120.0;
/// Largest message the server reads (a path of 1000 keyframes fits easily).
pub const MAX_MESSAGE_BYTES: usize = 1 << 20;

/// What an image shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Rgb,
    /// Expected depth through the turbo colour map (as `nerf render` writes it).
    Depth,
    Opacity,
}

impl Mode {
    pub fn code(self) -> u8 {
        match self {
            Mode::Rgb => 0,
            Mode::Depth => 1,
            Mode::Opacity => 2,
        }
    }
}

/// A camera as the page drives it: camera-to-world (3 rows of 4, OpenGL axes: looking down
/// -z, y up), vertical field of view in degrees, and the full-resolution image size.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewCamera {
    pub c2w: [[f32; 4]; 3],
    pub fov_y: f32,
    pub width: usize,
    pub height: usize,
}

/// A keyframe of a camera path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    pub c2w: [[f32; 4]; 3],
    pub fov_y: f32,
    /// Models of a moving scene: the moment this keyframe shows, in [0, 1] (time runs
    /// linearly between keyframes). A path keys time at every keyframe or at none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<f32>,
}

/// A camera path as the editor holds it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPath {
    pub keyframes: Vec<Keyframe>,
    pub seconds: f32,
    pub fps: f32,
    pub width: usize,
    pub height: usize,
    /// Whether the path returns to its first keyframe.
    #[serde(default)]
    pub looped: bool,
}

/// Messages from the page.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ClientMessage {
    /// Render this view: `seq` numbers the request (frames carry it back); `moving` says
    /// the camera is being dragged (render only the fast preview level).
    View {
        seq: u32,
        camera: ViewCamera,
        mode: Mode,
        #[serde(default)]
        moving: bool,
        /// Models trained with `--appearance`: colour with training photo `i`'s learned
        /// look; absent or null: the mean of the photos'.
        #[serde(default)]
        appearance: Option<u32>,
        /// Models of a moving scene: the moment to show, in [0, 1]; absent or null: 0.
        #[serde(default)]
        time: Option<f32>,
    },
    /// The smooth path through the keyframes, as poses (for the preview and scrubbing).
    PreviewPath { path: CameraPath },
    /// Save the path as `camera_paths/<name>.json` in the run folder (nerfstudio format).
    SavePath { name: String, path: CameraPath },
    /// Save the path, then render it to `renders/<name>/` and `renders/<name>.mp4` (or
    /// `.gif` without ffmpeg), reporting progress; `appearance` as for `View`.
    RenderPath {
        name: String,
        path: CameraPath,
        #[serde(default)]
        appearance: Option<u32>,
    },
}

/// Messages to the page.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    /// A request could not be served; the connection stays open.
    Error { message: String },
    /// The path's interpolated cameras (3x4 camera-to-world each), one per frame, and
    /// each frame's moment where the keyframes carry time.
    PathPoses {
        poses: Vec<[[f32; 4]; 3]>,
        fov_y: Vec<f32>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        times: Option<Vec<f32>>,
    },
    /// A path was saved (its location relative to the run folder).
    Saved { file: String },
    /// Rendering a path: frames done of all.
    RenderProgress { done: usize, total: usize },
    /// A path was rendered: the frames' folder and the video, relative to the run folder.
    Rendered {
        folder: String,
        video: Option<String>,
    },
    /// Training progress of a run being trained (`nerf train --view`).
    Training {
        step: u64,
        steps: u64,
        loss: f32,
        psnr: f64,
        rays_per_second: f64,
    },
}

/// Why a message from the page was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProtocolError {
    #[error("malformed message: {0}")]
    Malformed(String),
    #[error("{0}")]
    OutOfRange(String),
}

fn check_pose(c2w: &[[f32; 4]; 3], what: &str) -> Result<(), ProtocolError> {
    if c2w.iter().flatten().any(|v| !v.is_finite()) {
        return Err(ProtocolError::OutOfRange(format!(
            "{what}: the camera matrix has a non-finite value"
        )));
    }
    // The rotation part must be (close to) orthonormal.
    let col = |c: usize| [c2w[0][c], c2w[1][c], c2w[2][c]];
    for c in 0..3 {
        let v = col(c);
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if (len - 1.0).abs() > 1e-2 {
            return Err(ProtocolError::OutOfRange(format!(
                "{what}: the camera's rotation column {c} has length {len}, not 1"
            )));
        }
    }
    Ok(())
}

fn check_fov(fov_y: f32, what: &str) -> Result<(), ProtocolError> {
    if !(fov_y > 1.0 && fov_y < 170.0) {
        return Err(ProtocolError::OutOfRange(format!(
            "{what}: field of view {fov_y} degrees is not in (1, 170)"
        )));
    }
    Ok(())
}

fn check_size(width: usize, height: usize, what: &str) -> Result<(), ProtocolError> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(ProtocolError::OutOfRange(format!(
            "{what}: size {width}x{height} is not within 1..{MAX_SIDE} on each side"
        )));
    }
    if width * height > MAX_PIXELS {
        return Err(ProtocolError::OutOfRange(format!(
            "{what}: {width}x{height} is more than {MAX_PIXELS} pixels"
        )));
    }
    Ok(())
}

impl CameraPath {
    fn check(&self) -> Result<(), ProtocolError> {
        let n = self.keyframes.len();
        if !(2..=MAX_KEYFRAMES).contains(&n) {
            return Err(ProtocolError::OutOfRange(format!(
                "a camera path needs 2 to {MAX_KEYFRAMES} keyframes, not {n}"
            )));
        }
        for (k, key) in self.keyframes.iter().enumerate() {
            check_pose(&key.c2w, &format!("keyframe {k}"))?;
            check_fov(key.fov_y, &format!("keyframe {k}"))?;
            if let Some(t) = key.time.filter(|t| !(0.0..=1.0).contains(t)) {
                return Err(ProtocolError::OutOfRange(format!(
                    "keyframe {k}: time {t} is not a moment in [0, 1]"
                )));
            }
        }
        let timed = self.keyframes.iter().filter(|k| k.time.is_some()).count();
        if timed != 0 && timed != n {
            let untimed = self.keyframes.iter().position(|k| k.time.is_none());
            return Err(ProtocolError::OutOfRange(format!(
                "keyframe {} has no time while {timed} others have one: key time at every \
                 keyframe or at none",
                untimed.unwrap_or(0)
            )));
        }
        if !(self.seconds > 0.0 && self.seconds <= MAX_SECONDS) {
            return Err(ProtocolError::OutOfRange(format!(
                "duration {} s is not in (0, {MAX_SECONDS}]",
                self.seconds
            )));
        }
        if !(self.fps >= 1.0 && self.fps <= MAX_FPS) {
            return Err(ProtocolError::OutOfRange(format!(
                "frame rate {} is not in [1, {MAX_FPS}]",
                self.fps
            )));
        }
        check_size(self.width, self.height, "the path's render size")
    }

    /// Frames of the rendered path (at least two).
    pub fn frames(&self) -> usize {
        ((self.seconds * self.fps).round() as usize).max(2)
    }
}

/// A name for saved files: 1 to 64 letters, digits, `-` and `_` (so it can never leave
/// its folder).
pub fn check_name(name: &str) -> Result<(), ProtocolError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if ok {
        Ok(())
    } else {
        Err(ProtocolError::OutOfRange(format!(
            "name {name:?}: use 1 to 64 letters, digits, '-' or '_'"
        )))
    }
}

impl ClientMessage {
    /// A message from the page's text, checked.
    pub fn parse(text: &str) -> Result<ClientMessage, ProtocolError> {
        let msg: ClientMessage =
            serde_json::from_str(text).map_err(|e| ProtocolError::Malformed(e.to_string()))?;
        match &msg {
            ClientMessage::View { camera, time, .. } => {
                if let Some(t) = time.filter(|t| !(0.0..=1.0).contains(t)) {
                    return Err(ProtocolError::OutOfRange(format!(
                        "view: time {t} is not a moment in [0, 1]"
                    )));
                }
                check_pose(&camera.c2w, "view")?;
                check_fov(camera.fov_y, "view")?;
                check_size(camera.width, camera.height, "view")?;
            }
            ClientMessage::PreviewPath { path } => path.check()?,
            ClientMessage::SavePath { name, path }
            | ClientMessage::RenderPath { name, path, .. } => {
                check_name(name)?;
                path.check()?;
            }
        }
        Ok(msg)
    }
}

/// The header of a binary frame message: little-endian `seq` (u32), `width`, `height`
/// (u16 each), `mode` (u8), `final` (u8: 1 when this is the full-resolution frame of the
/// request), 2 reserved bytes, and the render time in microseconds (u32).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameHeader {
    pub seq: u32,
    pub width: u16,
    pub height: u16,
    pub mode: u8,
    pub last: bool,
    pub micros: u32,
}

pub const HEADER_BYTES: usize = 16;

impl FrameHeader {
    pub fn encode(&self) -> [u8; HEADER_BYTES] {
        let mut b = [0u8; HEADER_BYTES];
        b[0..4].copy_from_slice(&self.seq.to_le_bytes());
        b[4..6].copy_from_slice(&self.width.to_le_bytes());
        b[6..8].copy_from_slice(&self.height.to_le_bytes());
        b[8] = self.mode;
        b[9] = u8::from(self.last);
        b[12..16].copy_from_slice(&self.micros.to_le_bytes());
        b
    }

    pub fn decode(b: &[u8]) -> Option<FrameHeader> {
        let b = b.get(..HEADER_BYTES)?;
        let u32_at = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let u16_at = |i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
        Some(FrameHeader {
            seq: u32_at(0),
            width: u16_at(4),
            height: u16_at(6),
            mode: b[8],
            last: b[9] == 1,
            micros: u32_at(12),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,4]]";

    fn view(extra: &str) -> String {
        format!(
            r#"{{"type":"view","seq":3,"mode":"depth","camera":{{"c2w":{IDENTITY},"fov_y":40,"width":64,"height":48{extra}}}}}"#
        )
    }

    #[test]
    fn a_view_request_parses() {
        let m = ClientMessage::parse(&view("")).expect("parses");
        let ClientMessage::View {
            seq, mode, moving, ..
        } = m
        else {
            panic!("not a view: {m:?}")
        };
        assert_eq!((seq, mode, moving), (3, Mode::Depth, false));
        // A moving scene's moment travels with the request.
        let timed = view("").replace(r#""mode":"depth""#, r#""mode":"depth","time":0.25"#);
        let m = ClientMessage::parse(&timed).expect("parses");
        let ClientMessage::View { time, .. } = m else {
            panic!("not a view: {m:?}")
        };
        assert_eq!(time, Some(0.25));
    }

    #[test]
    fn malformed_and_out_of_range_messages_are_refused_with_a_reason() {
        let cases = [
            ("not json".to_string(), "malformed"),
            (r#"{"type":"fly"}"#.to_string(), "malformed"),
            (view(r#","extra":1"#), "malformed"),
            (view("").replace("\"width\":64", "\"width\":100000"), "size"),
            (view("").replace("\"width\":64", "\"width\":0"), "size"),
            (view("").replace("\"fov_y\":40", "\"fov_y\":0"), "field of view"),
            (view("").replace("[1,0,0,0]", "[2,0,0,0]"), "rotation"),
            (
                view("").replace(r#""mode":"depth""#, r#""mode":"depth","time":1.5"#),
                "time 1.5",
            ),
            (
                r#"{"type":"save_path","name":"../x","path":{"keyframes":[],"seconds":1,"fps":24,"width":8,"height":8}}"#
                    .to_string(),
                "name",
            ),
            (path_with_times("0.5", "1.5"), "keyframe 1: time 1.5"),
            (path_with_times("0.5", "null"), "keyframe 1 has no time"),
        ];
        for (text, why) in cases {
            let e = ClientMessage::parse(&text).expect_err(&text);
            assert!(e.to_string().contains(why), "{text}: {e}");
        }
    }

    /// A path preview of two keyframes whose `time`s are `a` and `b` (JSON values).
    fn path_with_times(a: &str, b: &str) -> String {
        let key =
            |t: &str| format!(r#"{{"c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,4]],"fov_y":40,"time":{t}}}"#);
        format!(
            r#"{{"type":"preview_path","path":{{"keyframes":[{},{}],"seconds":1,"fps":24,"width":8,"height":8}}}}"#,
            key(a),
            key(b)
        )
    }

    #[test]
    fn keyframes_carry_their_moment() {
        let m = ClientMessage::parse(&path_with_times("0.25", "0.75")).expect("parses");
        let ClientMessage::PreviewPath { path } = m else {
            panic!("not a preview");
        };
        let times: Vec<_> = path.keyframes.iter().map(|k| k.time).collect();
        assert_eq!(times, [Some(0.25), Some(0.75)]);
        let untimed = path_with_times("null", "null");
        assert!(ClientMessage::parse(&untimed).is_ok(), "a still path");
    }

    #[test]
    fn names_cannot_leave_their_folder() {
        for bad in [
            "",
            "..",
            "../a",
            "a/b",
            "a\\b",
            "a.json",
            &"x".repeat(65),
            "é",
        ] {
            assert!(check_name(bad).is_err(), "{bad:?}");
        }
        for good in ["orbit", "take-2", "A_1"] {
            assert!(check_name(good).is_ok(), "{good:?}");
        }
    }

    #[test]
    fn frame_headers_round_trip() {
        let h = FrameHeader {
            seq: 77,
            width: 640,
            height: 480,
            mode: 2,
            last: true,
            micros: 123_456,
        };
        assert_eq!(FrameHeader::decode(&h.encode()), Some(h));
        assert_eq!(FrameHeader::decode(&[0; 5]), None);
    }
}
