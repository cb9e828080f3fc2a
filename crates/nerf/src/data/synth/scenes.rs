//! The built-in furniture: a chair, a table and a lamp made of analytic primitives, each
//! inside roughly [-1.1, 1.1]^3 with +Z up (like the Blender scenes).

use super::materials::{Material, Pattern};
use super::shapes::Shape;

/// A primitive with its material.
#[derive(Clone, Copy, Debug)]
pub struct Part {
    pub shape: Shape,
    pub material: Material,
}

/// Which built-in scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SceneKind {
    Chair,
    Table,
    Lamp,
    /// The chair on a rug with a non-repeating pattern: enough texture for structure from
    /// motion (`nerf capture` tests), which the plain furniture lacks.
    Rug,
}

impl SceneKind {
    pub const ALL: [SceneKind; 4] = [
        SceneKind::Chair,
        SceneKind::Table,
        SceneKind::Lamp,
        SceneKind::Rug,
    ];

    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Chair => "chair",
            SceneKind::Table => "table",
            SceneKind::Lamp => "lamp",
            SceneKind::Rug => "rug",
        }
    }

    pub fn from_name(name: &str) -> Option<SceneKind> {
        SceneKind::ALL.into_iter().find(|k| k.name() == name)
    }

    pub fn parts(self) -> Vec<Part> {
        match self {
            SceneKind::Chair => chair(),
            SceneKind::Table => table(),
            SceneKind::Lamp => lamp(),
            SceneKind::Rug => rug(),
        }
    }
}

const OAK: Material = Material {
    pattern: Pattern::Wood {
        light: [0.78, 0.56, 0.33],
        dark: [0.45, 0.27, 0.12],
        axis: 2,
    },
    specular: 0.35,
    shininess: 40.0,
};

fn wood(axis: usize) -> Material {
    let mut m = OAK;
    if let Pattern::Wood { light, dark, .. } = OAK.pattern {
        m.pattern = Pattern::Wood { light, dark, axis };
    }
    m
}

const FABRIC: Material = Material {
    pattern: Pattern::Checker {
        a: [0.75, 0.12, 0.15],
        b: [0.92, 0.85, 0.7],
        cell: 0.12,
    },
    specular: 0.05,
    shininess: 8.0,
};

fn glossy(colour: [f32; 3]) -> Material {
    Material {
        pattern: Pattern::Solid(colour),
        specular: 0.8,
        shininess: 90.0,
    }
}

fn part(shape: Shape, material: Material) -> Part {
    Part { shape, material }
}

const RUG: Material = Material {
    pattern: Pattern::Noise {
        a: [0.1, 0.16, 0.35],
        b: [0.95, 0.8, 0.45],
        cell: 0.18,
    },
    specular: 0.02,
    shininess: 4.0,
};

fn rug() -> Vec<Part> {
    let mut parts = chair();
    parts.push(part(
        Shape::Box {
            center: [0.0, 0.0, -1.08],
            half: [1.3, 1.3, 0.03],
            round: 0.01,
        },
        RUG,
    ));
    parts
}

fn chair() -> Vec<Part> {
    let mut parts = vec![part(
        Shape::Box {
            center: [0.0, 0.0, -0.05],
            half: [0.55, 0.55, 0.07],
            round: 0.03,
        },
        FABRIC,
    )];
    for (x, y) in [(-0.45, -0.45), (0.45, -0.45), (-0.45, 0.45), (0.45, 0.45)] {
        parts.push(part(
            Shape::Cylinder {
                center: [x, y, -0.58],
                radius: 0.055,
                half_height: 0.47,
                axis: 2,
            },
            wood(2),
        ));
    }
    for x in [-0.45, 0.45] {
        parts.push(part(
            Shape::Cylinder {
                center: [x, 0.47, 0.47],
                radius: 0.05,
                half_height: 0.5,
                axis: 2,
            },
            wood(2),
        ));
        parts.push(part(
            Shape::Sphere {
                center: [x, 0.47, 1.0],
                radius: 0.08,
            },
            glossy([0.85, 0.7, 0.2]),
        ));
    }
    parts.push(part(
        Shape::Box {
            center: [0.0, 0.47, 0.62],
            half: [0.42, 0.04, 0.28],
            round: 0.02,
        },
        FABRIC,
    ));
    parts.push(part(
        Shape::Cylinder {
            center: [0.0, 0.47, 0.95],
            radius: 0.045,
            half_height: 0.45,
            axis: 0,
        },
        wood(0),
    ));
    parts.push(part(
        Shape::Torus {
            center: [0.0, 0.52, 0.62],
            major: 0.16,
            minor: 0.035,
            axis: 1,
        },
        glossy([0.15, 0.35, 0.75]),
    ));
    parts.push(part(
        Shape::Cylinder {
            center: [0.0, -0.45, -0.75],
            radius: 0.03,
            half_height: 0.45,
            axis: 0,
        },
        wood(0),
    ));
    parts
}

fn table() -> Vec<Part> {
    vec![
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, 0.25],
                radius: 0.95,
                half_height: 0.06,
                axis: 2,
            },
            wood(0),
        ),
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, -0.35],
                radius: 0.1,
                half_height: 0.55,
                axis: 2,
            },
            wood(2),
        ),
        part(
            Shape::Torus {
                center: [0.0, 0.0, -0.88],
                major: 0.42,
                minor: 0.07,
                axis: 2,
            },
            glossy([0.2, 0.2, 0.22]),
        ),
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, -0.9],
                radius: 0.42,
                half_height: 0.04,
                axis: 2,
            },
            wood(1),
        ),
        part(
            Shape::Sphere {
                center: [0.35, 0.2, 0.45],
                radius: 0.14,
            },
            glossy([0.8, 0.1, 0.1]),
        ),
        part(
            Shape::Sphere {
                center: [0.1, 0.42, 0.41],
                radius: 0.1,
            },
            glossy([0.9, 0.75, 0.1]),
        ),
        part(
            Shape::Box {
                center: [-0.35, -0.25, 0.35],
                half: [0.28, 0.2, 0.04],
                round: 0.01,
            },
            FABRIC,
        ),
    ]
}

fn lamp() -> Vec<Part> {
    let shade = Material {
        pattern: Pattern::Checker {
            a: [0.95, 0.9, 0.75],
            b: [0.3, 0.5, 0.35],
            cell: 0.15,
        },
        specular: 0.1,
        shininess: 10.0,
    };
    vec![
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, -0.95],
                radius: 0.45,
                half_height: 0.06,
                axis: 2,
            },
            glossy([0.25, 0.25, 0.3]),
        ),
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, -0.15],
                radius: 0.04,
                half_height: 0.78,
                axis: 2,
            },
            glossy([0.8, 0.75, 0.6]),
        ),
        part(
            Shape::Sphere {
                center: [0.0, 0.0, -0.45],
                radius: 0.12,
            },
            wood(2),
        ),
        part(
            Shape::Cylinder {
                center: [0.0, 0.0, 0.65],
                radius: 0.5,
                half_height: 0.3,
                axis: 2,
            },
            shade,
        ),
        part(
            Shape::Torus {
                center: [0.0, 0.0, 0.95],
                major: 0.5,
                minor: 0.035,
                axis: 2,
            },
            glossy([0.7, 0.55, 0.15]),
        ),
        part(
            Shape::Torus {
                center: [0.0, 0.0, 0.35],
                major: 0.5,
                minor: 0.035,
                axis: 2,
            },
            glossy([0.7, 0.55, 0.15]),
        ),
        part(
            Shape::Torus {
                center: [0.0, 0.0, -0.88],
                major: 0.4,
                minor: 0.03,
                axis: 2,
            },
            wood(0),
        ),
    ]
}
