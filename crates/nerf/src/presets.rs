//! Named configurations: the paper's model and the rows of its ablation table (NeRF,
//! Table 2, Realistic Synthetic 360), mip-NeRF's, D-NeRF's, FreeNeRF's and RegNeRF's models, and a reduced model for
//! quick CPU demos.

use crate::encoding::FrequencyEncoding;
use crate::error::{NerfError, Result};
use crate::field::{DeformationConfig, VanillaConfig};
use crate::model::free_nerf::FreeNerf;
use crate::model::reg_nerf::RegNerf;
use crate::model::VanillaModelConfig;

/// A named configuration of the model and the training views it sees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Preset {
    pub name: &'static str,
    pub help: &'static str,
    /// The PSNR the paper reports for this row (full-resolution Blender scenes), if any.
    pub paper_psnr: Option<f32>,
}

/// Every preset, in the order of the paper's table.
pub const PRESETS: &[Preset] = &[
    Preset {
        name: "paper",
        help:
            "the complete model: PE (L=10/4), view dependence, hierarchical 64+128 (paper 31.01 dB)",
        paper_psnr: Some(31.01),
    },
    Preset {
        name: "no-pe-vd-h",
        help: "raw xyz only: no PE, no view dependence, 256 coarse samples only (paper 26.67 dB)",
        paper_psnr: Some(26.67),
    },
    Preset {
        name: "no-pe",
        help: "no positional encoding of position or direction (paper 28.77 dB)",
        paper_psnr: Some(28.77),
    },
    Preset {
        name: "no-viewdirs",
        help: "colour independent of the view direction (paper 27.66 dB)",
        paper_psnr: Some(27.66),
    },
    Preset {
        name: "no-hierarchical",
        help: "one network with 256 stratified samples, no fine pass (paper 30.06 dB)",
        paper_psnr: Some(30.06),
    },
    Preset {
        name: "views-25",
        help: "the complete model trained on 25 of the training images (paper 27.78 dB)",
        paper_psnr: Some(27.78),
    },
    Preset {
        name: "views-50",
        help: "the complete model trained on 50 of the training images (paper 29.79 dB)",
        paper_psnr: Some(29.79),
    },
    Preset {
        name: "pe-5",
        help: "positional encoding with L=5 frequencies for position (paper 30.59 dB)",
        paper_psnr: Some(30.59),
    },
    Preset {
        name: "pe-15",
        help: "positional encoding with L=15 frequencies for position (paper 30.81 dB)",
        paper_psnr: Some(30.81),
    },
    Preset {
        name: "mip",
        help: "mip-NeRF: conical frustums, integrated PE (L=16), one network for both passes; not in the NeRF paper",
        paper_psnr: None,
    },
    Preset {
        name: "dnerf",
        help: "D-NeRF for moving scenes: a deformation MLP (8x256, PE of x and t, L=10) into the paper's canonical field, none at t=0; not in the NeRF paper",
        paper_psnr: None,
    },
    Preset {
        name: "freenerf",
        help: "FreeNeRF for few photos: the paper's model with its encoding's frequencies revealed over 90% of training and the density of each ray's first 10 samples penalised; not in the NeRF paper",
        paper_psnr: None,
    },
    Preset {
        name: "regnerf",
        help: "RegNeRF for few photos: the paper's model with depth smoothness on patches rendered from poses between the cameras and its samples' range widened over the first 256 steps; not in the NeRF paper",
        paper_psnr: None,
    },
    Preset {
        name: "demo",
        help: "reduced model for minutes on a CPU (4x64 trunk, 32+32 samples); not in the paper",
        paper_psnr: None,
    },
];

fn frequencies(l: usize) -> FrequencyEncoding {
    FrequencyEncoding {
        frequencies: l,
        paper_form: false,
    }
}

/// The paper's model: 8 x 256 trunk, skip after layer 4, L = 10 / 4, 64 + 128 samples.
pub fn paper() -> VanillaModelConfig {
    VanillaModelConfig {
        net: VanillaConfig::paper(),
        n_coarse: 64,
        n_fine: 128,
        integrated: false,
        shared_network: false,
        free_nerf: None,
        reg_nerf: None,
    }
}

/// Finds a preset by name.
/// The preset names with their one-line descriptions, for `--preset` (its `--help`).
pub fn possible_values() -> Vec<clap::builder::PossibleValue> {
    PRESETS
        .iter()
        .map(|p| clap::builder::PossibleValue::new(p.name).help(p.help))
        .collect()
}

pub fn find(name: &str) -> Result<&'static Preset> {
    PRESETS.iter().find(|p| p.name == name).ok_or_else(|| {
        let names: Vec<&str> = PRESETS.iter().map(|p| p.name).collect();
        NerfError::Config(format!(
            "unknown preset {name:?}; choose one of {}",
            names.join(", ")
        ))
    })
}

/// The model of a preset and how many training views it keeps (`None`: all).
pub fn build(name: &str) -> Result<(VanillaModelConfig, Option<usize>)> {
    let mut m = paper();
    let mut views = None;
    match find(name)?.name {
        "paper" => {}
        "no-pe-vd-h" => {
            m.net.position_encoding = frequencies(0);
            m.net.direction_encoding = None;
            m.n_coarse = 256;
            m.n_fine = 0;
        }
        "no-pe" => {
            m.net.position_encoding = frequencies(0);
            m.net.direction_encoding = Some(frequencies(0));
        }
        "no-viewdirs" => m.net.direction_encoding = None,
        "no-hierarchical" => {
            m.n_coarse = 256;
            m.n_fine = 0;
        }
        "views-25" => views = Some(25),
        "views-50" => views = Some(50),
        "pe-5" => m.net.position_encoding = frequencies(5),
        "pe-15" => m.net.position_encoding = frequencies(15),
        "mip" => {
            // mip-NeRF's 16 frequencies: the integrated encoding fades those finer than
            // each frustum, so high ones cost no aliasing.
            m.net.position_encoding = frequencies(16);
            m.integrated = true;
            m.shared_network = true;
        }
        "dnerf" => m.net.deformation = Some(DeformationConfig::dnerf()),
        "freenerf" => m.free_nerf = Some(FreeNerf::default()),
        "regnerf" => m.reg_nerf = Some(RegNerf::default()),
        "demo" => {
            m.net = VanillaConfig {
                depth: 4,
                width: 64,
                skip: Some(1),
                position_encoding: frequencies(8),
                direction_encoding: Some(frequencies(4)),
                view_width: 32,
                deformation: None,
            };
            m.n_coarse = 32;
            m.n_fine = 32;
        }
        other => unreachable!("preset {other} listed but not built"),
    }
    Ok((m, views))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_builds_and_differs_from_paper_as_named() {
        for p in PRESETS {
            let (m, views) = build(p.name).expect("preset builds");
            match p.name {
                "paper" => assert_eq!(m, paper()),
                "no-pe-vd-h" => assert!(
                    m.net.position_encoding.dims() == 3
                        && m.net.direction_encoding.is_none()
                        && !m.hierarchical()
                        && m.n_coarse == 256
                ),
                "no-pe" => assert_eq!(m.net.position_encoding.dims(), 3),
                "no-viewdirs" => assert!(m.net.direction_encoding.is_none() && m.hierarchical()),
                "no-hierarchical" => assert!(!m.hierarchical() && m.n_coarse == 256),
                "views-25" => assert_eq!(views, Some(25)),
                "views-50" => assert_eq!(views, Some(50)),
                "pe-5" => assert_eq!(m.net.position_encoding.dims(), 33),
                "pe-15" => assert_eq!(m.net.position_encoding.dims(), 93),
                "demo" => assert!(m.net.width < 256),
                "dnerf" => assert!(
                    m.net.deformation == Some(DeformationConfig::dnerf())
                        && m.net.width == 256
                        && m.hierarchical()
                ),
                "freenerf" => assert!(
                    m.free_nerf == Some(FreeNerf::default())
                        && m.net == paper().net
                        && m.hierarchical()
                ),
                "regnerf" => assert!(
                    m.reg_nerf == Some(RegNerf::default())
                        && m.free_nerf.is_none()
                        && m.net == paper().net
                        && m.hierarchical()
                ),
                "mip" => assert!(
                    m.integrated && m.shared_network && m.net.position_encoding.frequencies == 16
                ),
                _ => panic!("untested preset {}", p.name),
            }
        }
        assert!(find("nope").is_err());
    }
}
