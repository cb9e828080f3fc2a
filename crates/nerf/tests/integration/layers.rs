//! The library's modules import one way down: no circles, and the stages below the engine
//! seam know nothing above them. This reads the sources (`crate::` paths outside test
//! modules) so a new import that breaks a layer fails here, naming the file.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Top-level module of a source file (`src/render/march.rs` -> `render`).
fn module_of(rel: &Path) -> String {
    let first = rel
        .components()
        .next()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .unwrap_or_default();
    first.trim_end_matches(".rs").to_string()
}

/// Top-level modules a file names through `crate::` (comments and test modules left out).
fn imports(text: &str) -> BTreeSet<String> {
    let code: String = text
        .split("#[cfg(test)]")
        .next()
        .unwrap_or("")
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .flat_map(|l| [l, "\n"])
        .collect();
    let mut out = BTreeSet::new();
    let mut rest = code.as_str();
    while let Some(i) = rest.find("crate::") {
        rest = &rest[i + "crate::".len()..];
        let name: String = rest
            .chars()
            .take_while(|c| c.is_ascii_lowercase() || *c == '_')
            .collect();
        if !name.is_empty() {
            out.insert(name);
        }
    }
    out
}

fn sources(dir: &Path, root: &Path, out: &mut Vec<(String, String)>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            sources(&p, root, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            let rel = p.strip_prefix(root).unwrap_or(&p).to_path_buf();
            let text = std::fs::read_to_string(&p).unwrap_or_default();
            out.push((rel.display().to_string(), text));
        }
    }
}

/// Module -> modules it imports, with one file per edge for messages.
fn graph() -> BTreeMap<String, BTreeMap<String, String>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&root, &root, &mut files);
    assert!(files.len() > 50, "found only {} source files", files.len());
    let mut g: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    for (rel, text) in files {
        let m = module_of(Path::new(&rel));
        let edges = g.entry(m.clone()).or_default();
        for target in imports(&text) {
            // `error` is the shared error type, below everything.
            if target != m && target != "error" {
                edges.entry(target).or_insert_with(|| rel.clone());
            }
        }
    }
    g
}

#[test]
fn modules_import_one_way_with_no_circles() {
    let g = graph();
    // Depth-first search for a back edge.
    fn visit(
        m: &str,
        g: &BTreeMap<String, BTreeMap<String, String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) {
        if done.contains(m) {
            return;
        }
        if let Some(i) = path.iter().position(|p| p == m) {
            panic!("import circle: {} -> {m}", path[i..].join(" -> "));
        }
        path.push(m.to_string());
        for next in g.get(m).into_iter().flat_map(|e| e.keys()) {
            visit(next, g, path, done);
        }
        path.pop();
        done.insert(m.to_string());
    }
    let mut done = BTreeSet::new();
    for m in g.keys() {
        visit(m, &g, &mut Vec::new(), &mut done);
    }
}

#[test]
fn stages_below_the_seam_import_nothing_above_them() {
    let g = graph();
    // Each layer and everything it may import.
    let allowed: &[(&str, &[&str])] = &[
        ("stage", &["camera", "nn"]),
        ("render", &["stage", "math", "rng", "nn"]),
        ("field", &["stage", "encoding", "nn", "rng", "math"]),
        ("encoding", &["nn", "rng", "math"]),
        ("nn", &["rng", "math"]),
        ("camera", &["math", "io"]),
    ];
    for (layer, ok) in allowed {
        for (target, file) in g.get(*layer).into_iter().flatten() {
            assert!(
                ok.contains(&target.as_str()),
                "{file} ({layer}) imports {target}, which {layer} must not see"
            );
        }
    }
    // The first stage knows no rendering, model or engine; models know no engine or run.
    let forbidden: &[(&str, &[&str])] = &[
        (
            "data",
            &[
                "render", "field", "model", "engine", "views", "train", "eval", "mesh",
            ],
        ),
        (
            "model",
            &["engine", "train", "views", "eval", "mesh", "frames", "demo"],
        ),
        (
            "engine",
            &[
                "train",
                "views",
                "eval",
                "mesh",
                "frames",
                "demo",
                "checkpoint",
            ],
        ),
    ];
    for (layer, bad) in forbidden {
        for (target, file) in g.get(*layer).into_iter().flatten() {
            assert!(
                !bad.contains(&target.as_str()),
                "{file} ({layer}) imports {target}"
            );
        }
    }
}
