//! Anti-aliasing. A model trained on a scene at several scales (mip-NeRF's
//! multi-scale variant) must render its low-resolution views better when every sample
//! reads only the detail its pixel's footprint can hold than with point samples.

use crate::common::{chair_scene, cpu_run, fast_config};

use nerf::camera::footprint::reference_footprint;
use nerf::data::Split;
use nerf::field::fast::Antialias;
use nerf::model::ModelConfig;
use nerf::train::run::{self, LoadedRun};

const SCALES: usize = 3;

/// Trains the chair at 3 scales (64, 32 and 16 pixels) and evaluates it at the same
/// scales: the per-scale mean PSNRs, full resolution first.
fn train_multiscale(dir: &std::path::Path, antialias: bool) -> Vec<f32> {
    let data = dir.join("chair");
    if !data.exists() {
        chair_scene(&data, 64, 40, 3, 2);
    }
    let out = dir.join(if antialias { "aa" } else { "point" });
    let mut config = fast_config(&data, 600);
    config.multiscale = SCALES;
    let scene = config.open_scene(1).expect("scene");
    if let ModelConfig::Fast(m) = &mut config.model {
        // The box of the built-in scenes (1.5), the default 2^19 table's finest levels.
        m.field.grid.log2_table_size = 17;
        if antialias {
            m.field.antialias = Some(Antialias {
                reference_footprint: reference_footprint(
                    &scene.cameras(Split::Train),
                    &scene.space,
                    0.5 * m.field.bound,
                ),
            });
        }
    }
    run::train(&cpu_run(&out, config), &mut |_| {}).expect("train");
    let loaded = LoadedRun::open(&out).expect("open");
    let options = nerf::app::eval::EvalOptions {
        multiscale: SCALES,
        ..nerf::app::eval::EvalOptions::new(Split::Test, 1)
    };
    let report =
        nerf::app::eval::evaluate(&loaded, &options, &out.join("eval"), &|_| {}).expect("eval");
    assert_eq!(report.scales.len(), SCALES);
    assert_eq!(report.views.len(), 3 * SCALES);
    let psnr: Vec<f32> = report.scales.iter().map(|s| s.mean_psnr).collect();
    let mean = psnr.iter().sum::<f32>() / SCALES as f32;
    assert!((report.mean_psnr - mean).abs() < 1e-3, "{report:?}");
    psnr
}

/// A long quality run (two 600-step runs at three scales); CI checks anti-aliasing's
/// mechanics in the footprint tests and the GPU engine's agreement with the CPU's.
#[test]
#[ignore = "a long quality run, before a release: scripts/quality.sh tests"]
fn antialiasing_renders_the_low_scales_of_a_multiscale_scene_better() {
    let dir = tempfile::tempdir().expect("tempdir");
    let aa = train_multiscale(dir.path(), true);
    let point = train_multiscale(dir.path(), false);
    eprintln!("per-scale PSNR (1, 1/2, 1/4): anti-aliased {aa:?}, point samples {point:?}");
    assert!(
        aa[SCALES - 1] > point[SCALES - 1] + 0.5,
        "1/4 scale: anti-aliased {aa:?} vs point {point:?}"
    );
    assert!(aa[0] > point[0] - 0.5, "full scale: {aa:?} vs {point:?}");
}
