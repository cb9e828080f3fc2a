//! LPIPS (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual
//! Metric", CVPR 2018), the AlexNet variant the NeRF papers report (lower is better).
//!
//! Both images (RGB in [0, 1]) go to `[-1, 1]`, are shifted and scaled per channel, and pass
//! through AlexNet's five convolutions (each with its ReLU; max-pooling 3x3, stride 2 before
//! the second and third). At each of the five outputs, every pixel's feature vector is
//! divided by its length (plus 1e-10), the squared difference of the two images' unit
//! features is weighted per channel by a learned non-negative linear head, summed over the
//! channels and averaged over the pixels; LPIPS is the sum over the five layers.
//!
//! The weights (torchvision's ImageNet AlexNet and the `lpips` package's heads) cannot ship
//! with us; `scripts/lpips_weights.py` writes them into the safetensors file that
//! [`Lpips::load`] reads: `conv{1..5}.weight` (`[out, in, k, k]`), `conv{1..5}.bias`
//! (`[out]`) and `lin{1..5}.weight` (`[channels]`), all f32.
//!
//! Work mapping: each convolution is one matrix product of the image's patches (im2col,
//! channels last) with the kernel, split over the rayon threads by `gemm`.

use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors};

use crate::error::{NerfError, Result};
use crate::nn::linalg::{matmul_parallel, MatRef};

/// The network's input normalisation: `(x - SHIFT) / SCALE` per channel, after `2x - 1`.
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Added to each feature vector's length before dividing by it.
const EPS: f32 = 1e-10;

/// One convolution of AlexNet's feature extractor: its shape and whether a 3x3, stride-2
/// max-pool comes before it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvShape {
    pub inputs: usize,
    pub outputs: usize,
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
    pub pool_before: bool,
}

/// AlexNet's five convolutions (torchvision's `alexnet().features`).
pub const ALEXNET: [ConvShape; 5] = [
    conv(3, 64, 11, 4, 2, false),
    conv(64, 192, 5, 1, 2, true),
    conv(192, 384, 3, 1, 1, true),
    conv(384, 256, 3, 1, 1, false),
    conv(256, 256, 3, 1, 1, false),
];

const fn conv(
    inputs: usize,
    outputs: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    pool_before: bool,
) -> ConvShape {
    ConvShape {
        inputs,
        outputs,
        kernel,
        stride,
        padding,
        pool_before,
    }
}

/// One layer's weights: the kernel as a `(k * k * inputs) x outputs` matrix whose rows run
/// over (ky, kx, channel), matching the patches' layout, its bias, and the LPIPS head.
#[derive(Clone, Debug)]
struct Layer {
    shape: ConvShape,
    kernel: Vec<f32>,
    bias: Vec<f32>,
    head: Vec<f32>,
}

/// An image with channels last: `height x width x channels`.
#[derive(Clone, Debug)]
struct Map {
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<f32>,
}

/// The LPIPS network, ready to compare images.
#[derive(Clone, Debug)]
pub struct Lpips {
    layers: Vec<Layer>,
}

impl Lpips {
    /// Reads the weights written by `scripts/lpips_weights.py` (see the module docs),
    /// checking every tensor's presence, type and shape.
    pub fn load(path: &Path) -> Result<Lpips> {
        let bytes = std::fs::read(path).map_err(|e| NerfError::io(path, e))?;
        let problem = |message: String| NerfError::Format {
            path: path.to_path_buf(),
            message,
        };
        let st = SafeTensors::deserialize(&bytes)
            .map_err(|e| problem(format!("not a safetensors file of LPIPS weights: {e}")))?;
        let tensor = |name: &str, shape: &[usize]| -> Result<Vec<f32>> {
            let t = st.tensor(name).map_err(|_| {
                problem(format!(
                    "no tensor {name}: not LPIPS weights written by scripts/lpips_weights.py"
                ))
            })?;
            if t.dtype() != Dtype::F32 || t.shape() != shape {
                return Err(problem(format!(
                    "{name} is {:?} {:?}, expected F32 {shape:?}",
                    t.dtype(),
                    t.shape()
                )));
            }
            let values: Vec<f32> = t
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            if values.iter().any(|v| !v.is_finite()) {
                return Err(problem(format!("{name} holds a non-finite value")));
            }
            Ok(values)
        };
        let mut layers = Vec::new();
        for (i, shape) in ALEXNET.iter().enumerate() {
            let (o, c, k) = (shape.outputs, shape.inputs, shape.kernel);
            let weight = tensor(&format!("conv{}.weight", i + 1), &[o, c, k, k])?;
            let bias = tensor(&format!("conv{}.bias", i + 1), &[o])?;
            let head = tensor(&format!("lin{}.weight", i + 1), &[o])?;
            layers.push(Layer::new(*shape, &weight, bias, head));
        }
        Ok(Lpips { layers })
    }

    /// Builds the network from weights in PyTorch's layout (`conv[i]`: `[out, in, k, k]`,
    /// row-major), for tests and converters.
    pub fn from_weights(convs: &[(Vec<f32>, Vec<f32>)], heads: &[Vec<f32>]) -> Lpips {
        let layers = ALEXNET
            .iter()
            .zip(convs)
            .zip(heads)
            .map(|((shape, (w, b)), h)| Layer::new(*shape, w, b.clone(), h.clone()))
            .collect();
        Lpips { layers }
    }

    /// LPIPS between two packed RGB images in [0, 1] of `width x height` (0: the same
    /// image). Images smaller than the network's reach (about 32 pixels a side) are refused.
    pub fn distance(&self, a: &[f32], b: &[f32], width: usize, height: usize) -> Result<f32> {
        Ok(self.per_layer(a, b, width, height)?.iter().sum())
    }

    /// The five layers' parts of [`distance`](Self::distance).
    pub fn per_layer(&self, a: &[f32], b: &[f32], width: usize, height: usize) -> Result<Vec<f32>> {
        if a.len() != width * height * 3 || b.len() != a.len() {
            return Err(NerfError::Config(format!(
                "LPIPS of images of {} and {} values, expected {width}x{height}x3",
                a.len(),
                b.len()
            )));
        }
        if width < 32 || height < 32 {
            return Err(NerfError::Config(format!(
                "LPIPS needs images of at least 32x32 pixels, not {width}x{height}"
            )));
        }
        let mut fa = self.input(a, width, height);
        let mut fb = self.input(b, width, height);
        let mut parts = Vec::with_capacity(self.layers.len());
        for layer in &self.layers {
            fa = layer.forward(&fa);
            fb = layer.forward(&fb);
            parts.push(layer.score(&fa, &fb) as f32);
        }
        Ok(parts)
    }

    fn input(&self, rgb: &[f32], width: usize, height: usize) -> Map {
        let data = rgb
            .chunks_exact(3)
            .flat_map(|p| {
                std::array::from_fn::<f32, 3, _>(|c| (2.0 * p[c] - 1.0 - SHIFT[c]) / SCALE[c])
            })
            .collect();
        Map {
            width,
            height,
            channels: 3,
            data,
        }
    }
}

impl Layer {
    fn new(shape: ConvShape, weight: &[f32], bias: Vec<f32>, head: Vec<f32>) -> Layer {
        let (o, c, k) = (shape.outputs, shape.inputs, shape.kernel);
        // [out][in][ky][kx] -> rows (ky, kx, in), columns out.
        let mut kernel = vec![0.0; k * k * c * o];
        for oc in 0..o {
            for ic in 0..c {
                for ky in 0..k {
                    for kx in 0..k {
                        let row = (ky * k + kx) * c + ic;
                        kernel[row * o + oc] = weight[((oc * c + ic) * k + ky) * k + kx];
                    }
                }
            }
        }
        Layer {
            shape,
            kernel,
            bias,
            head,
        }
    }

    /// Max-pool (when the layer has one), convolution, bias and ReLU.
    fn forward(&self, input: &Map) -> Map {
        let pooled;
        let x = if self.shape.pool_before {
            pooled = max_pool(input);
            &pooled
        } else {
            input
        };
        let ConvShape {
            outputs: o,
            kernel: k,
            stride: s,
            padding: p,
            ..
        } = self.shape;
        let c = x.channels;
        let ow = (x.width + 2 * p - k) / s + 1;
        let oh = (x.height + 2 * p - k) / s + 1;
        let cols = k * k * c;
        let mut patches = vec![0.0; ow * oh * cols];
        for oy in 0..oh {
            for ox in 0..ow {
                let row = &mut patches[(oy * ow + ox) * cols..][..cols];
                for ky in 0..k {
                    let y = (oy * s + ky) as isize - p as isize;
                    if y < 0 || y >= x.height as isize {
                        continue;
                    }
                    for kx in 0..k {
                        let xx = (ox * s + kx) as isize - p as isize;
                        if xx < 0 || xx >= x.width as isize {
                            continue;
                        }
                        let from = (y as usize * x.width + xx as usize) * c;
                        row[(ky * k + kx) * c..][..c].copy_from_slice(&x.data[from..][..c]);
                    }
                }
            }
        }
        let mut data = vec![0.0; ow * oh * o];
        let threads = rayon::current_num_threads();
        matmul_parallel(
            &mut data,
            MatRef::new(&patches, ow * oh, cols),
            MatRef::new(&self.kernel, cols, o),
            threads,
        );
        for px in data.chunks_exact_mut(o) {
            for (v, b) in px.iter_mut().zip(&self.bias) {
                *v = (*v + b).max(0.0);
            }
        }
        Map {
            width: ow,
            height: oh,
            channels: o,
            data,
        }
    }

    /// This layer's part of LPIPS: the head-weighted squared difference of the two maps'
    /// unit feature vectors, summed over channels and averaged over pixels.
    fn score(&self, a: &Map, b: &Map) -> f64 {
        let c = a.channels;
        let unit = |v: &[f32]| {
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            1.0 / (norm + EPS)
        };
        let mut total = 0.0f64;
        for (pa, pb) in a.data.chunks_exact(c).zip(b.data.chunks_exact(c)) {
            let (na, nb) = (unit(pa), unit(pb));
            let d: f32 = pa
                .iter()
                .zip(pb)
                .zip(&self.head)
                .map(|((x, y), w)| w * (x * na - y * nb).powi(2))
                .sum();
            total += d as f64;
        }
        total / (a.width * a.height) as f64
    }
}

/// 3x3 max-pooling with stride 2 and no padding (sizes round down).
fn max_pool(x: &Map) -> Map {
    let (w, h, c) = ((x.width - 3) / 2 + 1, (x.height - 3) / 2 + 1, x.channels);
    let mut data = vec![f32::NEG_INFINITY; w * h * c];
    for oy in 0..h {
        for ox in 0..w {
            let out = &mut data[(oy * w + ox) * c..][..c];
            for ky in 0..3 {
                for kx in 0..3 {
                    let from = ((oy * 2 + ky) * x.width + ox * 2 + kx) * c;
                    for (o, v) in out.iter_mut().zip(&x.data[from..][..c]) {
                        *o = o.max(*v);
                    }
                }
            }
        }
    }
    Map {
        width: w,
        height: h,
        channels: c,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixture's generator (see `scripts/lpips_fixture.py`): value `i` of stream `s`,
    /// uniform in [0, 1), from the 24 high bits of `splitmix64(s << 32 | i)`.
    fn uniform(stream: u64, n: usize) -> Vec<f64> {
        (0..n as u64)
            .map(|i| {
                let mut z = ((stream << 32) | i).wrapping_add(0x9E37_79B9_7F4A_7C15);
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                (z >> 40) as f64 / (1u64 << 24) as f64
            })
            .collect()
    }

    fn fixture_network() -> Lpips {
        let mut convs = Vec::new();
        let mut heads = Vec::new();
        for (k, shape) in ALEXNET.iter().enumerate() {
            let s = 3 * k as u64;
            let fan_in = shape.inputs * shape.kernel * shape.kernel;
            let bound = (6.0 / fan_in as f64).sqrt();
            let w = uniform(s, shape.outputs * fan_in)
                .iter()
                .map(|u| ((2.0 * u - 1.0) * bound) as f32)
                .collect();
            let b = uniform(s + 1, shape.outputs)
                .iter()
                .map(|u| ((2.0 * u - 1.0) * 0.1) as f32)
                .collect();
            convs.push((w, b));
            heads.push(
                uniform(s + 2, shape.outputs)
                    .iter()
                    .map(|u| (u * 0.1) as f32)
                    .collect(),
            );
        }
        Lpips::from_weights(&convs, &heads)
    }

    /// Against the `lpips` package (PyTorch) on the same random weights and
    /// images, per layer and in total, to 1e-4 relative (f32 sums in another order).
    #[test]
    fn matches_the_lpips_package_on_a_random_network() {
        let fixture: serde_json::Value =
            serde_json::from_str(include_str!("../../tests/fixtures/lpips_random.json"))
                .expect("fixture");
        let number = |v: &serde_json::Value| v.as_f64().expect("number");
        let (w, h) = (
            number(&fixture["width"]) as usize,
            number(&fixture["height"]) as usize,
        );
        let n = w * h * 3;
        let a: Vec<f32> = uniform(100, n).iter().map(|&u| u as f32).collect();
        let b: Vec<f32> = uniform(101, n)
            .iter()
            .zip(&a)
            .map(|(u, &x)| (x + (0.2 * (2.0 * u - 1.0)) as f32).clamp(0.0, 1.0))
            .collect();
        let net = fixture_network();
        let parts = net.per_layer(&a, &b, w, h).expect("lpips");
        let expected: Vec<f64> = fixture["per_layer"]
            .as_array()
            .expect("per_layer")
            .iter()
            .map(number)
            .collect();
        for (got, want) in parts.iter().zip(&expected) {
            let rel = (*got as f64 - want).abs() / want.abs();
            assert!(rel < 1e-4, "layer: {got} vs {want} ({parts:?})");
        }
        let total = net.distance(&a, &b, w, h).expect("lpips") as f64;
        let want = number(&fixture["lpips"]);
        assert!((total - want).abs() / want < 1e-4, "{total} vs {want}");
        assert_eq!(net.distance(&a, &a, w, h).expect("same"), 0.0);
        assert!(
            net.distance(&a, &a, 20, 20).is_err(),
            "wrong size is refused"
        );
    }

    /// Missing files, files of other tensors and tensors of the wrong shape are errors
    /// naming the file and the tensor.
    #[test]
    fn weight_files_are_checked() {
        let dir = tempfile::tempdir().expect("tempdir");
        let missing = dir.path().join("none.safetensors");
        let err = Lpips::load(&missing).expect_err("missing");
        assert!(err.to_string().contains("none.safetensors"), "{err}");
        let junk = dir.path().join("junk.safetensors");
        std::fs::write(&junk, b"not a tensor file").expect("write");
        let err = Lpips::load(&junk).expect_err("junk");
        assert!(err.to_string().contains("not a safetensors file"), "{err}");
        let wrong = dir.path().join("wrong.safetensors");
        let data = vec![0u8; 4 * 8];
        let view = safetensors::tensor::TensorView::new(Dtype::F32, vec![8], &data).expect("view");
        let bytes = safetensors::serialize([("conv1.weight", view)], None).expect("serialize");
        std::fs::write(&wrong, bytes).expect("write");
        let err = Lpips::load(&wrong).expect_err("wrong shape");
        assert!(err.to_string().contains("conv1.weight is F32 [8]"), "{err}");
    }
}
