//! COLMAP sparse models: `cameras`, `images` and `points3D`, in COLMAP's binary (`.bin`)
//! or text (`.txt`) form, read and written without COLMAP itself.
//!
//! COLMAP stores world-to-camera poses (`x_cam = R(q) x_world + t`, quaternion `q = (w, x,
//! y, z)`) with OpenCV axes (the camera looks down +Z, +Y down in the image);
//! [`Image::camera_to_world`] turns one into our OpenGL camera-to-world pose.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use crate::camera::Pose;
use crate::error::{NerfError, Result};

/// COLMAP camera models, with their ids in the binary format and parameter counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    Opencv,
    OpencvFisheye,
    /// Any other model COLMAP knows (read so the file parses; refused when used).
    Other(i32),
}

impl CameraModel {
    const NAMED: [(CameraModel, i32, &'static str, usize); 6] = [
        (CameraModel::SimplePinhole, 0, "SIMPLE_PINHOLE", 3),
        (CameraModel::Pinhole, 1, "PINHOLE", 4),
        (CameraModel::SimpleRadial, 2, "SIMPLE_RADIAL", 4),
        (CameraModel::Radial, 3, "RADIAL", 5),
        (CameraModel::Opencv, 4, "OPENCV", 8),
        (CameraModel::OpencvFisheye, 5, "OPENCV_FISHEYE", 8),
    ];
    /// Parameter counts of COLMAP's other models (ids 6..10).
    const OTHER_PARAMS: [(i32, &'static str, usize); 5] = [
        (6, "FULL_OPENCV", 12),
        (7, "FOV", 5),
        (8, "SIMPLE_RADIAL_FISHEYE", 4),
        (9, "RADIAL_FISHEYE", 5),
        (10, "THIN_PRISM_FISHEYE", 12),
    ];

    pub fn from_id(id: i32) -> Option<CameraModel> {
        Self::NAMED
            .iter()
            .find(|m| m.1 == id)
            .map(|m| m.0)
            .or_else(|| {
                Self::OTHER_PARAMS
                    .iter()
                    .any(|m| m.0 == id)
                    .then_some(CameraModel::Other(id))
            })
    }

    pub fn from_name(name: &str) -> Option<CameraModel> {
        Self::NAMED
            .iter()
            .find(|m| m.2 == name)
            .map(|m| m.0)
            .or_else(|| {
                Self::OTHER_PARAMS
                    .iter()
                    .find(|m| m.1 == name)
                    .map(|m| CameraModel::Other(m.0))
            })
    }

    pub fn name(self) -> &'static str {
        match self {
            CameraModel::Other(id) => Self::OTHER_PARAMS
                .iter()
                .find(|m| m.0 == id)
                .map_or("UNKNOWN", |m| m.1),
            m => Self::NAMED
                .iter()
                .find(|n| n.0 == m)
                .map_or("UNKNOWN", |n| n.2),
        }
    }

    pub fn num_params(self) -> usize {
        match self {
            CameraModel::Other(id) => Self::OTHER_PARAMS
                .iter()
                .find(|m| m.0 == id)
                .map_or(0, |m| m.2),
            m => Self::NAMED.iter().find(|n| n.0 == m).map_or(0, |n| n.3),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub id: u32,
    pub model: CameraModel,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub id: u32,
    /// World-to-camera rotation as a unit quaternion (w, x, y, z).
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
    /// The 3-D points this image observes (ids into `Model::points`).
    pub point_ids: Vec<u64>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Model {
    pub cameras: BTreeMap<u32, Camera>,
    pub images: Vec<Image>,
    pub points: Vec<Point>,
}

impl Image {
    /// World-to-camera rotation matrix (OpenCV axes).
    pub fn rotation(&self) -> [[f64; 3]; 3] {
        let n = self
            .qvec
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt()
            .max(1e-300);
        let [w, x, y, z] = self.qvec.map(|v| v / n);
        [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ]
    }

    /// The camera's centre in the world, `-R^T t`.
    pub fn centre(&self) -> [f64; 3] {
        let r = self.rotation();
        let t = self.tvec;
        [0, 1, 2].map(|c| -(r[0][c] * t[0] + r[1][c] * t[1] + r[2][c] * t[2]))
    }

    /// Camera-to-world pose with OpenGL axes (Y and Z of the OpenCV camera flipped).
    pub fn camera_to_world(&self) -> Pose {
        let r = self.rotation();
        let c = self.centre();
        let mut pose = [[0.0f32; 4]; 3];
        for (row, out) in pose.iter_mut().enumerate() {
            // Columns of R^T are the rows of R.
            *out = [
                r[0][row] as f32,
                -r[1][row] as f32,
                -r[2][row] as f32,
                c[row] as f32,
            ];
        }
        pose
    }

    /// The image whose camera has OpenGL camera-to-world `pose` (inverse of
    /// [`Image::camera_to_world`]).
    pub fn from_camera_to_world(id: u32, camera_id: u32, name: &str, pose: &Pose) -> Image {
        let mut r = [[0.0f64; 3]; 3];
        for (row, out) in r.iter_mut().enumerate() {
            let sign = if row == 0 { 1.0 } else { -1.0 };
            *out = [0, 1, 2].map(|c| sign * pose[c][row] as f64);
        }
        let c = [0, 1, 2].map(|k| pose[k][3] as f64);
        let tvec = [0, 1, 2].map(|k| -(r[k][0] * c[0] + r[k][1] * c[1] + r[k][2] * c[2]));
        Image {
            id,
            qvec: quaternion(&r),
            tvec,
            camera_id,
            name: name.to_string(),
            point_ids: Vec::new(),
        }
    }

    /// Depth (along the optical axis) of a world point in this camera.
    pub fn depth_of(&self, p: [f64; 3]) -> f64 {
        let r = self.rotation();
        r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + self.tvec[2]
    }
}

/// The unit quaternion (w, x, y, z) of a rotation matrix.
fn quaternion(r: &[[f64; 3]; 3]) -> [f64; 4] {
    let trace = r[0][0] + r[1][1] + r[2][2];
    let q = if trace > 0.0 {
        let s = 0.5 / (trace + 1.0).sqrt();
        [
            0.25 / s,
            (r[2][1] - r[1][2]) * s,
            (r[0][2] - r[2][0]) * s,
            (r[1][0] - r[0][1]) * s,
        ]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = 2.0 * (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt();
        [
            (r[2][1] - r[1][2]) / s,
            0.25 * s,
            (r[0][1] + r[1][0]) / s,
            (r[0][2] + r[2][0]) / s,
        ]
    } else if r[1][1] > r[2][2] {
        let s = 2.0 * (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt();
        [
            (r[0][2] - r[2][0]) / s,
            (r[0][1] + r[1][0]) / s,
            0.25 * s,
            (r[1][2] + r[2][1]) / s,
        ]
    } else {
        let s = 2.0 * (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt();
        [
            (r[1][0] - r[0][1]) / s,
            (r[0][2] + r[2][0]) / s,
            (r[1][2] + r[2][1]) / s,
            0.25 * s,
        ]
    };
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    q.map(|v| v * sign)
}

/// The folder of the sparse model in a scene folder: `sparse/0`, `sparse`, or the folder
/// itself, whichever holds `cameras.bin` or `cameras.txt`.
pub fn find_model(dir: &Path) -> Option<PathBuf> {
    [dir.join("sparse/0"), dir.join("sparse"), dir.to_path_buf()]
        .into_iter()
        .find(|d| d.join("cameras.bin").exists() || d.join("cameras.txt").exists())
}

/// The sparse model of scene folder `dir` ([`find_model`]) and the folder it is in, or an
/// error naming `dir`.
pub fn open_model(dir: &Path) -> Result<(PathBuf, Model)> {
    let model_dir = find_model(dir).ok_or_else(|| {
        NerfError::format(
            dir,
            "has no COLMAP model (sparse/0/cameras.bin or cameras.txt)",
        )
    })?;
    let model = read_model(&model_dir)?;
    Ok((model_dir, model))
}

/// Reads the model in `dir` (binary files preferred when both forms are present).
/// `points3D` is optional.
pub fn read_model(dir: &Path) -> Result<Model> {
    let binary = dir.join("cameras.bin").exists();
    let ext = if binary { "bin" } else { "txt" };
    let path = |name: &str| dir.join(format!("{name}.{ext}"));
    let points_path = path("points3D");
    let (cameras, images, points) = if binary {
        let cameras = binary::cameras(&path("cameras"))?;
        let images = binary::images(&path("images"))?;
        let points = if points_path.exists() {
            binary::points(&points_path)?
        } else {
            Vec::new()
        };
        (cameras, images, points)
    } else {
        let cameras = text::cameras(&path("cameras"))?;
        let images = text::images(&path("images"))?;
        let points = if points_path.exists() {
            text::points(&points_path)?
        } else {
            Vec::new()
        };
        (cameras, images, points)
    };
    let model = Model {
        cameras,
        images,
        points,
    };
    if let Some(img) = model
        .images
        .iter()
        .find(|i| !model.cameras.contains_key(&i.camera_id))
    {
        return Err(NerfError::format(
            path("images"),
            format!(
                "image {} ({}) uses camera {}, which cameras.{ext} does not define",
                img.id, img.name, img.camera_id
            ),
        ));
    }
    Ok(model)
}

/// Writes the model as COLMAP text files (`cameras.txt`, `images.txt`, `points3D.txt`).
pub fn write_text_model(dir: &Path, model: &Model) -> Result<()> {
    crate::io::create_dir(dir)?;
    let mut cams = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    for c in model.cameras.values() {
        let params: Vec<String> = c.params.iter().map(|p| p.to_string()).collect();
        cams += &format!(
            "{} {} {} {} {}\n",
            c.id,
            c.model.name(),
            c.width,
            c.height,
            params.join(" ")
        );
    }
    let mut imgs = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for i in &model.images {
        let [qw, qx, qy, qz] = i.qvec;
        let [tx, ty, tz] = i.tvec;
        imgs += &format!(
            "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}\n",
            i.id, i.camera_id, i.name
        );
        let obs: Vec<String> = i.point_ids.iter().map(|p| format!("0 0 {p}")).collect();
        imgs += &obs.join(" ");
        imgs.push('\n');
    }
    let mut pts =
        String::from("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    for p in &model.points {
        let [x, y, z] = p.xyz;
        let [r, g, b] = p.rgb;
        pts += &format!("{} {x} {y} {z} {r} {g} {b} {}\n", p.id, p.error);
    }
    crate::io::write_atomic(&dir.join("cameras.txt"), cams.as_bytes())?;
    crate::io::write_atomic(&dir.join("images.txt"), imgs.as_bytes())?;
    crate::io::write_atomic(&dir.join("points3D.txt"), pts.as_bytes())
}

mod text {
    use super::*;

    fn lines(path: &Path) -> Result<Vec<(usize, String)>> {
        let text = std::fs::read_to_string(path).map_err(|e| NerfError::io(path, e))?;
        Ok(text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim().to_string()))
            .filter(|(_, l)| !l.starts_with('#'))
            .collect())
    }

    fn num<T: std::str::FromStr>(
        path: &Path,
        line: usize,
        field: &str,
        s: Option<&str>,
    ) -> Result<T> {
        let s =
            s.ok_or_else(|| NerfError::format(path, format!("line {line}: missing {field}")))?;
        s.parse().map_err(|_| {
            NerfError::format(path, format!("line {line}: {field} {s:?} is not a number"))
        })
    }

    pub fn cameras(path: &Path) -> Result<BTreeMap<u32, Camera>> {
        let mut out = BTreeMap::new();
        for (n, line) in lines(path)? {
            if line.is_empty() {
                continue;
            }
            let mut f = line.split_whitespace();
            let id = num(path, n, "CAMERA_ID", f.next())?;
            let name = f.next().unwrap_or_default();
            let model = CameraModel::from_name(name).ok_or_else(|| {
                NerfError::format(path, format!("line {n}: unknown camera model {name:?}"))
            })?;
            let width = num(path, n, "WIDTH", f.next())?;
            let height = num(path, n, "HEIGHT", f.next())?;
            let params = f
                .map(|s| num(path, n, "PARAMS", Some(s)))
                .collect::<Result<Vec<f64>>>()?;
            if params.len() != model.num_params() {
                return Err(NerfError::format(
                    path,
                    format!(
                        "line {n}: {name} takes {} parameters, got {}",
                        model.num_params(),
                        params.len()
                    ),
                ));
            }
            out.insert(
                id,
                Camera {
                    id,
                    model,
                    width,
                    height,
                    params,
                },
            );
        }
        Ok(out)
    }

    pub fn images(path: &Path) -> Result<Vec<Image>> {
        let all = lines(path)?;
        let mut out = Vec::new();
        let mut it = all.into_iter();
        while let Some((n, line)) = it.next() {
            if line.is_empty() {
                continue;
            }
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() < 10 {
                return Err(NerfError::format(
                    path,
                    format!("line {n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
                ));
            }
            let v = |k: usize, name: &str| num::<f64>(path, n, name, Some(f[k]));
            let id = num(path, n, "IMAGE_ID", Some(f[0]))?;
            let qvec = [v(1, "QW")?, v(2, "QX")?, v(3, "QY")?, v(4, "QZ")?];
            let tvec = [v(5, "TX")?, v(6, "TY")?, v(7, "TZ")?];
            let camera_id = num(path, n, "CAMERA_ID", Some(f[8]))?;
            // Names may contain spaces: the rest of the line.
            let name = f[9..].join(" ");
            let mut point_ids = Vec::new();
            if let Some((n2, obs)) = it.next() {
                let o: Vec<&str> = obs.split_whitespace().collect();
                for triple in o.chunks(3) {
                    if let [_, _, id] = triple {
                        let id: i64 = num(path, n2, "POINT3D_ID", Some(id))?;
                        if id >= 0 {
                            point_ids.push(id as u64);
                        }
                    }
                }
            }
            out.push(Image {
                id,
                qvec,
                tvec,
                camera_id,
                name,
                point_ids,
            });
        }
        Ok(out)
    }

    pub fn points(path: &Path) -> Result<Vec<Point>> {
        let mut out = Vec::new();
        for (n, line) in lines(path)? {
            if line.is_empty() {
                continue;
            }
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() < 8 {
                return Err(NerfError::format(
                    path,
                    format!("line {n}: expected POINT3D_ID X Y Z R G B ERROR"),
                ));
            }
            let v = |k: usize, name: &str| num::<f64>(path, n, name, Some(f[k]));
            let c = |k: usize, name: &str| num::<u8>(path, n, name, Some(f[k]));
            out.push(Point {
                id: num(path, n, "POINT3D_ID", Some(f[0]))?,
                xyz: [v(1, "X")?, v(2, "Y")?, v(3, "Z")?],
                rgb: [c(4, "R")?, c(5, "G")?, c(6, "B")?],
                error: v(7, "ERROR")?,
            });
        }
        Ok(out)
    }
}

mod binary {
    use super::*;

    /// A little-endian cursor that names the file when it runs out.
    struct Reader<'a> {
        path: &'a Path,
        bytes: &'a [u8],
        at: usize,
    }

    impl<'a> Reader<'a> {
        fn take(&mut self, n: usize) -> Result<&'a [u8]> {
            let end = self
                .at
                .checked_add(n)
                .filter(|&e| e <= self.bytes.len())
                .ok_or_else(|| {
                    NerfError::format(
                        self.path,
                        format!("truncated at byte {} (wanted {n} more)", self.at),
                    )
                })?;
            let s = &self.bytes[self.at..end];
            self.at = end;
            Ok(s)
        }
        fn arr<const N: usize>(&mut self) -> Result<[u8; N]> {
            let mut a = [0u8; N];
            a.copy_from_slice(self.take(N)?);
            Ok(a)
        }
        fn u64(&mut self) -> Result<u64> {
            Ok(u64::from_le_bytes(self.arr()?))
        }
        fn i64(&mut self) -> Result<i64> {
            Ok(i64::from_le_bytes(self.arr()?))
        }
        fn i32(&mut self) -> Result<i32> {
            Ok(i32::from_le_bytes(self.arr()?))
        }
        fn u32(&mut self) -> Result<u32> {
            Ok(u32::from_le_bytes(self.arr()?))
        }
        fn f64(&mut self) -> Result<f64> {
            Ok(f64::from_le_bytes(self.arr()?))
        }
        /// A count that must fit in the rest of the file (`min_size` bytes per item), so a
        /// corrupt file cannot ask for a huge allocation.
        fn count(&mut self, min_size: usize) -> Result<usize> {
            let n = self.u64()?;
            let left = (self.bytes.len() - self.at) as u64;
            if n.saturating_mul(min_size as u64) > left {
                return Err(NerfError::format(
                    self.path,
                    format!("claims {n} entries, more than the file holds"),
                ));
            }
            Ok(n as usize)
        }
    }

    fn read(path: &Path) -> Result<Vec<u8>> {
        let mut bytes = Vec::new();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|e| NerfError::io(path, e))?;
        Ok(bytes)
    }

    pub fn cameras(path: &Path) -> Result<BTreeMap<u32, Camera>> {
        let bytes = read(path)?;
        let mut r = Reader {
            path,
            bytes: &bytes,
            at: 0,
        };
        let n = r.count(24)?;
        let mut out = BTreeMap::new();
        for _ in 0..n {
            let id = r.u32()?;
            let model_id = r.i32()?;
            let model = CameraModel::from_id(model_id).ok_or_else(|| {
                NerfError::format(path, format!("camera {id}: unknown model id {model_id}"))
            })?;
            let width = r.u64()?;
            let height = r.u64()?;
            let params = (0..model.num_params())
                .map(|_| r.f64())
                .collect::<Result<Vec<_>>>()?;
            out.insert(
                id,
                Camera {
                    id,
                    model,
                    width,
                    height,
                    params,
                },
            );
        }
        Ok(out)
    }

    pub fn images(path: &Path) -> Result<Vec<Image>> {
        let bytes = read(path)?;
        let mut r = Reader {
            path,
            bytes: &bytes,
            at: 0,
        };
        let n = r.count(64)?;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            let id = r.u32()?;
            let qvec = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
            let tvec = [r.f64()?, r.f64()?, r.f64()?];
            let camera_id = r.u32()?;
            let mut name = Vec::new();
            loop {
                match r.take(1)?[0] {
                    0 => break,
                    b => name.push(b),
                }
            }
            let name = String::from_utf8_lossy(&name).into_owned();
            let m = r.count(24)?;
            let mut point_ids = Vec::new();
            for _ in 0..m {
                r.take(16)?; // x, y
                let p = r.i64()?;
                if p >= 0 {
                    point_ids.push(p as u64);
                }
            }
            out.push(Image {
                id,
                qvec,
                tvec,
                camera_id,
                name,
                point_ids,
            });
        }
        Ok(out)
    }

    pub fn points(path: &Path) -> Result<Vec<Point>> {
        let bytes = read(path)?;
        let mut r = Reader {
            path,
            bytes: &bytes,
            at: 0,
        };
        let n = r.count(43)?;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            let id = r.u64()?;
            let xyz = [r.f64()?, r.f64()?, r.f64()?];
            let rgb = r.arr::<3>()?;
            let error = r.f64()?;
            let track = r.count(8)?;
            r.take(track * 8)?;
            out.push(Point {
                id,
                xyz,
                rgb,
                error,
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;

    #[test]
    fn pose_round_trips_through_colmap_convention() {
        let pose = look_at([1.0, -3.0, 2.0], [0.2, 0.1, 0.0], [0.0, 0.0, 1.0]);
        let img = Image::from_camera_to_world(1, 1, "a.png", &pose);
        let back = img.camera_to_world();
        for r in 0..3 {
            for c in 0..4 {
                assert!(
                    (back[r][c] - pose[r][c]).abs() < 1e-5,
                    "{back:?} vs {pose:?}"
                );
            }
        }
        // The point looked at is in front of the camera (positive OpenCV depth).
        assert!(img.depth_of([0.2, 0.1, 0.0]) > 3.0);
    }

    #[test]
    fn text_model_round_trips_and_errors_name_the_line() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut model = Model::default();
        model.cameras.insert(
            3,
            Camera {
                id: 3,
                model: CameraModel::Opencv,
                width: 64,
                height: 48,
                params: vec![50.0, 51.0, 32.0, 24.0, 0.01, -0.02, 0.001, 0.002],
            },
        );
        let pose = look_at([0.0, -4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let mut img = Image::from_camera_to_world(7, 3, "my photo.png", &pose);
        img.point_ids = vec![1, 2];
        model.images.push(img);
        model.points.push(Point {
            id: 1,
            xyz: [0.1, 0.2, 0.3],
            rgb: [10, 20, 30],
            error: 0.5,
        });
        model.points.push(Point {
            id: 2,
            xyz: [-0.1, 0.0, 0.3],
            rgb: [1, 2, 3],
            error: 0.25,
        });
        write_text_model(dir.path(), &model).expect("write");
        let back = read_model(dir.path()).expect("read");
        assert_eq!(back.cameras, model.cameras);
        assert_eq!(back.points, model.points);
        assert_eq!(back.images[0].name, "my photo.png");
        assert_eq!(back.images[0].point_ids, vec![1, 2]);
        for k in 0..4 {
            assert!((back.images[0].qvec[k] - model.images[0].qvec[k]).abs() < 1e-12);
        }

        std::fs::write(dir.path().join("cameras.txt"), "1 PINHOLE 64 48 50 50 32\n")
            .expect("write");
        let err = read_model(dir.path()).expect_err("3 params").to_string();
        assert!(
            err.contains("cameras.txt") && err.contains("line 1") && err.contains("4 parameters"),
            "{err}"
        );
        std::fs::write(
            dir.path().join("cameras.txt"),
            "1 PINHOLE 64 48 50 50 32 24\n",
        )
        .expect("write");
        let err = read_model(dir.path())
            .expect_err("camera 3 missing")
            .to_string();
        assert!(err.contains("camera 3"), "{err}");
    }

    #[test]
    fn truncated_binary_is_an_error_not_a_panic() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut bytes = 5u64.to_le_bytes().to_vec();
        bytes.extend_from_slice(&[0u8; 30]);
        std::fs::write(dir.path().join("cameras.bin"), &bytes).expect("write");
        std::fs::write(dir.path().join("images.bin"), 0u64.to_le_bytes()).expect("write");
        let err = read_model(dir.path()).expect_err("truncated").to_string();
        assert!(err.contains("cameras.bin"), "{err}");
        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend_from_slice(&[0u8; 8]);
        std::fs::write(dir.path().join("cameras.bin"), &huge).expect("write");
        let err = read_model(dir.path()).expect_err("huge count").to_string();
        assert!(err.contains("more than the file holds"), "{err}");
    }
}
