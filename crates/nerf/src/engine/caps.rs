//! What each engine can run: the one table the rest of the code asks. A run's defaults
//! (`train::defaults`) turn a feature on only where its engine runs it; opening an engine
//! for a configuration that uses a feature the engine lacks is refused by name, with the
//! way out; `--device auto` says when such a run goes to the CPU. A feature that gains
//! kernels on an engine changes its row here and nowhere else.

use crate::model::ModelConfig;

/// The engines.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EngineKind {
    /// The CPU engine: every feature.
    Cpu,
    /// The GPU engine (wgpu or CUDA).
    Gpu,
}

/// A feature of a run that not every engine may run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Feature {
    /// Cone footprints and the scale-aware hash grid (`--antialias`, `--multiscale`).
    Antialias,
    /// A learned appearance code per training photo (`--appearance`).
    Appearance,
    /// Pose corrections learned with the field (`--refine-cameras`), and eval's fitting of
    /// the test poses that follows from it.
    CameraRefinement,
    /// mip-NeRF 360's distortion loss (`--distortion`).
    Distortion,
    /// The paper model's integrated positional encoding and shared network (`--preset mip`).
    Mip,
    /// Few-view training: the space too few photos see kept empty (`--few-view`).
    FewView,
    /// The fast model's field of space and time for a moving scene (`--dynamic`).
    Dynamic,
    /// D-NeRF's deformation network before the paper's field (`--preset dnerf`).
    DNerf,
    /// FreeNeRF's frequency mask and occlusion penalty (`--preset freenerf`).
    FreeNerf,
    /// RegNeRF's depth smoothness on patches from unseen poses (`--depth-smoothness`).
    DepthSmoothness,
    /// RegNeRF's depth smoothness and sample-space annealing for the paper's model
    /// (`--preset regnerf`).
    RegNerf,
    /// The fast model's networks trained with bfloat16 inputs and `f32` sums (`--bf16`).
    Bf16Products,
}

/// Which engine runs which feature: `(feature, CPU, GPU)`.
const TABLE: [(Feature, bool, bool); 12] = [
    (Feature::Antialias, true, true),
    (Feature::Appearance, true, true),
    (Feature::CameraRefinement, true, true),
    (Feature::Distortion, true, true),
    (Feature::Mip, true, true),
    (Feature::FewView, true, true),
    (Feature::Dynamic, true, true),
    (Feature::DNerf, true, true),
    (Feature::FreeNerf, true, true),
    (Feature::DepthSmoothness, true, true),
    (Feature::RegNerf, true, true),
    (Feature::Bf16Products, true, false),
];

impl Feature {
    /// Every feature, in the table's order.
    pub const ALL: [Feature; 12] = [
        Feature::Antialias,
        Feature::Appearance,
        Feature::CameraRefinement,
        Feature::Distortion,
        Feature::Mip,
        Feature::FewView,
        Feature::Dynamic,
        Feature::DNerf,
        Feature::FreeNerf,
        Feature::DepthSmoothness,
        Feature::RegNerf,
        Feature::Bf16Products,
    ];

    /// Its name and the flags that ask for it and turn it off, for messages.
    pub fn describe(self) -> &'static str {
        match self {
            Feature::Antialias => "anti-aliasing (--antialias; turned off by --no-antialias)",
            Feature::Appearance => {
                "per-photo appearance codes (--appearance; turned off by --no-appearance)"
            }
            Feature::CameraRefinement => {
                "camera refinement (--refine-cameras; turned off by --no-refine-cameras)"
            }
            Feature::Distortion => {
                "the distortion loss (--distortion; turned off by --no-distortion)"
            }
            Feature::Mip => "mip-NeRF's frustums and shared network (--preset mip)",
            Feature::FewView => "few-view training (--few-view; turned off by --no-few-view)",
            Feature::Dynamic => {
                "the moving scene's field of space and time (--dynamic; --no-dynamic trains a \
                 still one)"
            }
            Feature::DNerf => "D-NeRF's deformation network (--preset dnerf)",
            Feature::FreeNerf => {
                "FreeNeRF's frequency mask and occlusion penalty (--preset freenerf)"
            }
            Feature::DepthSmoothness => {
                "RegNeRF's depth smoothness on patches from unseen poses (--depth-smoothness)"
            }
            Feature::RegNerf => {
                "RegNeRF's depth smoothness and sample-space annealing for the paper's model \
                 (--preset regnerf)"
            }
            Feature::Bf16Products => {
                "the networks' products in bfloat16 (--bf16; turned off by --no-bf16)"
            }
        }
    }

    /// The features `model` uses.
    pub fn used_by(model: &ModelConfig) -> Vec<Feature> {
        Feature::ALL
            .into_iter()
            .filter(|f| match (f, model) {
                (Feature::Antialias, ModelConfig::Fast(c)) => c.field.antialias.is_some(),
                (Feature::Appearance, ModelConfig::Fast(c)) => c.field.appearance_dims > 0,
                (Feature::CameraRefinement, ModelConfig::Fast(c)) => c.refine_cameras.is_some(),
                (Feature::Distortion, ModelConfig::Fast(c)) => c.distortion > 0.0,
                (Feature::FewView, ModelConfig::Fast(c)) => c.few_view.is_some(),
                (Feature::DepthSmoothness, ModelConfig::Fast(c)) => c.depth_smoothness.is_some(),
                (Feature::Dynamic, ModelConfig::Fast(c)) => c.field.motion.is_some(),
                (Feature::DNerf, ModelConfig::Vanilla(c)) => c.net.deformation.is_some(),
                (Feature::Mip, ModelConfig::Vanilla(c)) => c.integrated || c.shared_network,
                (Feature::FreeNerf, ModelConfig::Vanilla(c)) => c.free_nerf.is_some(),
                (Feature::RegNerf, ModelConfig::Vanilla(c)) => c.reg_nerf.is_some(),
                (Feature::Bf16Products, ModelConfig::Fast(c)) => c.bf16_products,
                _ => false,
            })
            .collect()
    }
}

impl EngineKind {
    /// Whether this engine runs `feature`.
    pub fn runs(self, feature: Feature) -> bool {
        TABLE
            .iter()
            .find(|(f, ..)| *f == feature)
            .is_some_and(|&(_, cpu, gpu)| match self {
                EngineKind::Cpu => cpu,
                EngineKind::Gpu => gpu,
            })
    }

    /// The features `model` uses that this engine does not run.
    pub fn missing(self, model: &ModelConfig) -> Vec<Feature> {
        Feature::used_by(model)
            .into_iter()
            .filter(|&f| !self.runs(f))
            .collect()
    }

    /// "the CPU engine" / "the GPU engine", for messages.
    pub fn name(self) -> &'static str {
        match self {
            EngineKind::Cpu => "the CPU engine",
            EngineKind::Gpu => "the GPU engine",
        }
    }
}

/// `features`, described and joined for a sentence ("a, b and c").
pub fn list(features: &[Feature]) -> String {
    let names: Vec<&str> = features.iter().map(|f| f.describe()).collect();
    match names.split_last() {
        None => String::new(),
        Some((last, [])) => (*last).to_string(),
        Some((last, rest)) => format!("{} and {last}", rest.join(", ")),
    }
}

/// Why `engine` cannot run `model`, naming each feature it lacks and the way out; `None`
/// when it can.
pub fn refusal(engine: EngineKind, model: &ModelConfig) -> Option<String> {
    let missing = engine.missing(model);
    (!missing.is_empty()).then(|| refusal_of(engine, &missing))
}

/// The refusal of `engine` for the features `missing` (at least one): what it lacks and
/// the way out.
fn refusal_of(engine: EngineKind, missing: &[Feature]) -> String {
    let one = missing.len() == 1;
    format!(
        "{} {} not run on {} yet: use --device cpu (a new run can also leave {} out)",
        list(missing),
        if one { "does" } else { "do" },
        engine.name(),
        if one { "it" } else { "them" },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FastModelConfig;

    #[test]
    fn every_feature_has_one_row_and_the_cpu_runs_them_all() {
        for f in Feature::ALL {
            assert_eq!(TABLE.iter().filter(|(g, ..)| *g == f).count(), 1, "{f:?}");
            assert!(EngineKind::Cpu.runs(f), "{f:?}");
        }
    }

    #[test]
    fn a_plain_model_runs_everywhere_and_each_feature_is_named() {
        let plain = ModelConfig::Fast(FastModelConfig::default());
        assert!(Feature::used_by(&plain).is_empty());
        assert_eq!(refusal(EngineKind::Gpu, &plain), None);
        let mut fast = FastModelConfig {
            distortion: 1e-4,
            ..FastModelConfig::default()
        };
        fast.field.appearance_dims = 16;
        let model = ModelConfig::Fast(fast);
        assert_eq!(
            Feature::used_by(&model),
            [Feature::Appearance, Feature::Distortion]
        );
        assert_eq!(refusal(EngineKind::Cpu, &model), None);
        let gpu_missing = EngineKind::Gpu.missing(&model);
        let why = refusal(EngineKind::Gpu, &model).unwrap_or_default();
        for f in &gpu_missing {
            assert!(why.contains(f.describe()), "{why}");
        }
        assert!(
            gpu_missing.is_empty() || why.contains("--device cpu"),
            "{why}"
        );
    }

    #[test]
    fn the_mip_preset_is_a_feature_of_the_paper_model() {
        let preset = |name| ModelConfig::Vanilla(crate::presets::build(name).expect(name).0);
        assert_eq!(Feature::used_by(&preset("mip")), [Feature::Mip]);
        assert_eq!(Feature::used_by(&preset("freenerf")), [Feature::FreeNerf]);
        assert_eq!(refusal(EngineKind::Gpu, &preset("freenerf")), None);
        assert_eq!(Feature::used_by(&preset("dnerf")), [Feature::DNerf]);
        assert_eq!(refusal(EngineKind::Gpu, &preset("dnerf")), None);
        assert_eq!(Feature::used_by(&preset("regnerf")), [Feature::RegNerf]);
        assert_eq!(refusal(EngineKind::Gpu, &preset("regnerf")), None);
        assert_eq!(Feature::used_by(&preset("paper")), []);
    }

    /// Every feature that changes what a model learns runs on both engines today (the
    /// GPU's products are f32 only); a refusal names each missing one and the way out.
    #[test]
    fn a_refusal_names_what_is_missing_and_the_way_out() {
        for f in Feature::ALL {
            assert_eq!(EngineKind::Gpu.runs(f), f != Feature::Bf16Products, "{f:?}");
        }
        let bf16 = ModelConfig::Fast(FastModelConfig {
            bf16_products: true,
            ..FastModelConfig::default()
        });
        let why = refusal(EngineKind::Gpu, &bf16).unwrap_or_default();
        assert!(
            why.contains("--bf16") && why.contains("--device cpu"),
            "{why}"
        );
        let one = refusal_of(EngineKind::Gpu, &[Feature::DNerf]);
        assert_eq!(
            one,
            format!(
                "{} does not run on the GPU engine yet: use --device cpu (a new run can also \
                 leave it out)",
                Feature::DNerf.describe()
            )
        );
        let two = refusal_of(EngineKind::Gpu, &[Feature::Mip, Feature::RegNerf]);
        assert!(
            two.contains(" and ") && two.contains(" do not run ") && two.ends_with("them out)")
        );
    }

    #[test]
    fn lists_read_as_sentences() {
        assert_eq!(list(&[]), "");
        assert_eq!(list(&[Feature::Mip]), Feature::Mip.describe());
        let three = list(&[Feature::Antialias, Feature::Appearance, Feature::Mip]);
        assert!(
            three.contains("), per-photo") && three.contains(") and mip-NeRF"),
            "{three}"
        );
    }
}
