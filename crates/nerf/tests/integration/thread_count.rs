//! The same seed gives the same run for any thread count. From the same state a step draws
//! the same rays and samples (ray `k` of step `s` is a function of the seed, `s` and `k`;
//! the fast model's marching blocks are fixed) and computes the same loss, bit for bit
//! (squared errors are summed per ray, in ray order). The gradients agree up to the order in
//! which the threads' sums are added (float reassociation), so over many steps parameters
//! and losses agree closely, and the fast model's sample counts agree exactly until an
//! occupancy refresh thresholds densities that differ in their last bits.

use crate::common::{fast_config, small_scene};

use nerf::data::Split;
use nerf::train::{TrainConfig, Trainer};

/// Trains `steps` steps on `threads` threads; returns each step's (loss, rays, samples) and
/// the final parameters.
fn train_on(
    threads: usize,
    config: &TrainConfig,
    steps: usize,
) -> (Vec<(f32, usize, usize)>, Vec<f32>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    pool.install(|| {
        let data = config
            .open_scene(1)
            .and_then(|s| s.load(Split::Train, 1))
            .expect("scene");
        let mut trainer = Trainer::new(config.clone(), data).expect("trainer");
        assert_eq!(trainer.engine.describe(), format!("cpu, {threads} threads"));
        let stats = (0..steps)
            .map(|_| {
                let s = trainer.step().expect("step");
                (s.loss, s.rays, s.samples)
            })
            .collect();
        (stats, trainer.engine.state().params)
    })
}

/// Relative distance of two parameter vectors.
fn relative_difference(a: &[f32], b: &[f32]) -> f64 {
    let (mut diff, mut norm) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        diff += ((x - y) as f64).powi(2);
        norm += (*x as f64).powi(2);
    }
    (diff / norm.max(1e-30)).sqrt()
}

/// `exact_until`: steps before which rays and samples must match exactly (the fast
/// model's first occupancy refresh); after it they may differ by 1%.
fn assert_thread_count_independent(config: &TrainConfig, steps: usize, exact_until: usize) {
    let (one, p1) = train_on(1, config, steps);
    for threads in [2, 3] {
        let (other, p) = train_on(threads, config, steps);
        // The first step starts from the same weights: the same loss, bit for bit.
        assert_eq!(
            one[0].0, other[0].0,
            "first loss differs at {threads} threads"
        );
        for (k, (a, b)) in one.iter().zip(&other).enumerate() {
            if k < exact_until {
                assert_eq!(
                    (a.1, a.2),
                    (b.1, b.2),
                    "step {k}: rays / samples differ (1 vs {threads} threads)"
                );
            } else {
                let close = |x: usize, y: usize| x.abs_diff(y) * 100 <= x.max(1);
                assert!(
                    close(a.1, b.1) && close(a.2, b.2),
                    "step {k}: rays / samples {a:?} vs {b:?}"
                );
            }
            let tol = if k < exact_until { 1e-3 } else { 2e-2 };
            assert!(
                (a.0 - b.0).abs() <= tol * a.0.abs(),
                "step {k}: loss {} vs {} ({threads} threads)",
                a.0,
                b.0
            );
        }
        let d = relative_difference(&p1, &p);
        assert!(
            d < 1e-2,
            "parameters after {steps} steps differ by {d:e} (1 vs {threads} threads)"
        );
        eprintln!("{threads} threads: parameters after {steps} steps differ from 1 thread's by {d:.2e} (relative)");
    }
}

#[test]
fn fast_model_gives_the_same_run_for_any_thread_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 24);
    let mut config = fast_config(&data, 50);
    // Several chunks per step, so the chunks really are spread over the threads.
    if let nerf::model::ModelConfig::Fast(m) = &mut config.model {
        m.batch_samples = 1 << 10;
    }
    // The occupancy grid is first refreshed after step 16.
    assert_thread_count_independent(&config, 50, 16);
}

#[test]
fn vanilla_model_gives_the_same_run_for_any_thread_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 16);
    let mut config = TrainConfig::from_preset(data, "demo").expect("preset");
    if let nerf::model::ModelConfig::Vanilla(m) = &mut config.model {
        m.net.width = 32;
        m.n_coarse = 16;
        m.n_fine = 16;
    }
    config.batch_rays = 128;
    config.chunk_rays = 16;
    config.val_every = 0;
    // A fixed number of rays and samples per ray.
    assert_thread_count_independent(&config, 50, 50);
}
