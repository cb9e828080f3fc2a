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

/// A source file's code: its test module and comment lines left out.
fn code_of(text: &str) -> String {
    text.split("#[cfg(test)]")
        .next()
        .unwrap_or("")
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .flat_map(|l| [l, "\n"])
        .collect()
}

/// Top-level modules a file names through `crate::` (comments and test modules left out).
fn imports(text: &str) -> BTreeSet<String> {
    let code = code_of(text);
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

/// A circle in `g` (each name to the names it imports), as the path around it.
fn circle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if done.contains(n) {
            return None;
        }
        if let Some(i) = path.iter().position(|p| p == n) {
            let mut found = path[i..].to_vec();
            found.push(n.to_string());
            return Some(found);
        }
        path.push(n.to_string());
        for next in g.get(n).into_iter().flatten() {
            if let Some(found) = visit(next, g, path, done) {
                return Some(found);
            }
        }
        path.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    g.keys()
        .find_map(|n| visit(n, g, &mut Vec::new(), &mut done))
}

#[test]
fn modules_import_one_way_with_no_circles() {
    let g: BTreeMap<String, BTreeSet<String>> = graph()
        .into_iter()
        .map(|(m, edges)| (m, edges.into_keys().collect()))
        .collect();
    if let Some(found) = circle(&g) {
        panic!("import circle: {}", found.join(" -> "));
    }
}

#[test]
fn a_circle_is_found() {
    let edges = |pairs: &[(&str, &str)]| {
        let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (a, b) in pairs {
            g.entry(a.to_string()).or_default().insert(b.to_string());
        }
        g
    };
    assert_eq!(circle(&edges(&[("a", "b"), ("b", "c"), ("a", "c")])), None);
    let found = circle(&edges(&[("a", "b"), ("b", "c"), ("c", "a")])).expect("a circle");
    assert_eq!(found.first(), found.last());
    assert_eq!(found.len(), 4);
}

#[test]
fn stages_below_the_seam_import_nothing_above_them() {
    let g = graph();
    // The applications sit on the top floor: nothing in the core imports them.
    for (module, edges) in &g {
        if let Some(file) = edges.get("app").filter(|_| module != "app") {
            panic!("{file} ({module}) imports app, which the core must not see");
        }
    }
    // Each layer and everything it may import (`math`, `simd` and `step_clock` are leaves:
    // they import nothing of the crate).
    let allowed: &[(&str, &[&str])] = &[
        ("stage", &["camera", "nn"]),
        (
            "render",
            &["stage", "math", "simd", "step_clock", "rng", "nn"],
        ),
        (
            "field",
            &[
                "stage",
                "encoding",
                "nn",
                "rng",
                "math",
                "simd",
                "step_clock",
            ],
        ),
        ("encoding", &["nn", "rng", "math", "simd", "step_clock"]),
        ("nn", &["rng", "math", "simd", "step_clock"]),
        ("camera", &["math", "simd", "io"]),
        ("math", &[]),
        ("simd", &[]),
        ("step_clock", &[]),
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

/// The file a module path names: the longest prefix of `segments` that is a file under
/// `src` (`a/b.rs` or `a/b/mod.rs`), `lib.rs` for the crate root.
fn file_of(files: &BTreeSet<String>, segments: &[String]) -> Option<String> {
    (0..=segments.len()).rev().find_map(|n| {
        let stem = segments[..n].join("/");
        if n == 0 {
            return Some("lib.rs".to_string());
        }
        [format!("{stem}.rs"), format!("{stem}/mod.rs")]
            .into_iter()
            .find(|f| files.contains(f))
    })
}

/// The module path of a source file (`data/scene.rs` -> `[data, scene]`, `data/mod.rs` ->
/// `[data]`, `lib.rs` -> `[]`).
fn module_path(rel: &str) -> Vec<String> {
    let stem = rel.trim_end_matches(".rs");
    let mut parts: Vec<String> = stem.split('/').map(str::to_string).collect();
    if parts.last().is_some_and(|p| p == "mod" || p == "lib") {
        parts.pop();
    }
    parts
}

/// Identifier path segments that follow `prefix` in `code`, up to a `{` group, each group
/// member that is itself a path contributing its own first segment.
fn paths_after(code: &str, prefix: &str) -> Vec<Vec<String>> {
    let ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find(prefix) {
        let before = rest[..i].chars().next_back();
        rest = &rest[i + prefix.len()..];
        if before.is_some_and(|c| ident(c) || c == ':') {
            continue;
        }
        let mut segments = Vec::new();
        let mut s = rest;
        loop {
            let name: String = s.chars().take_while(|&c| ident(c)).collect();
            if name.is_empty() {
                break;
            }
            s = &s[name.len()..];
            segments.push(name);
            match s.strip_prefix("::") {
                Some(after) => s = after,
                None => break,
            }
        }
        if let Some(group) = s.strip_prefix('{') {
            let inner = &group[..group.find('}').unwrap_or(group.len())];
            for member in inner.split(',') {
                let name: String = member.trim().chars().take_while(|&c| ident(c)).collect();
                if !name.is_empty() && name != "self" {
                    let mut p = segments.clone();
                    p.push(name);
                    out.push(p);
                }
            }
        }
        out.push(segments);
    }
    out
}

/// File -> files it imports (through `crate::`, `super::`, and a `mod.rs`'s own children).
fn file_graph() -> BTreeMap<String, BTreeSet<String>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut sources_read = Vec::new();
    sources(&root, &root, &mut sources_read);
    let files: BTreeSet<String> = sources_read.iter().map(|(rel, _)| rel.clone()).collect();
    let mut g = BTreeMap::new();
    for (rel, text) in &sources_read {
        let code = code_of(text);
        let is_parent = rel.ends_with("mod.rs") || rel == "lib.rs";
        // A parent's `pub use` only gives an item of a child a shorter name (the usual
        // shape: the trait in `mod.rs`, its implementations in children that import it),
        // so it is no edge; what the parent's own code names is.
        let code: String = code
            .lines()
            .filter(|l| !(is_parent && l.trim_start().starts_with("pub use ")))
            .flat_map(|l| [l, "\n"])
            .collect();
        let here = module_path(rel);
        let mut targets = BTreeSet::new();
        let mut add = |segments: Vec<String>| {
            if let Some(f) = file_of(&files, &segments) {
                // The crate root and `error` (the shared error type) sit below everything.
                if f != *rel && f != "lib.rs" && f != "error.rs" {
                    targets.insert(f);
                }
            }
        };
        for p in paths_after(&code, "crate::") {
            add(p);
        }
        for p in paths_after(&code, "super::") {
            let mut base = here.clone();
            base.pop();
            let mut p = p.as_slice();
            while p.first().is_some_and(|s| s == "super") {
                base.pop();
                p = &p[1..];
            }
            base.extend(p.iter().cloned());
            add(base);
        }
        // A `mod.rs` (or `lib.rs`) reaches its children by their bare names.
        for line in code.lines().filter(|l| l.contains("use ") && is_parent) {
            for p in paths_after(line, "use ") {
                let mut child = here.clone();
                child.extend(p);
                if child.len() > here.len() + 1 {
                    add(child);
                }
            }
        }
        g.insert(rel.clone(), targets);
    }
    g
}

#[test]
fn files_import_one_way_with_no_circles() {
    let g = file_graph();
    assert!(
        g.get("data/scene.rs")
            .is_some_and(|t| t.contains("data/blender.rs")),
        "the file graph lost a known edge (data/scene.rs -> data/blender.rs): {:?}",
        g.get("data/scene.rs")
    );
    if let Some(found) = circle(&g) {
        panic!("import circle between files: {}", found.join(" -> "));
    }
}

#[test]
fn the_file_graph_reads_paths_as_rust_does() {
    let files: BTreeSet<String> = ["a/mod.rs", "a/b.rs", "a/c.rs"]
        .into_iter()
        .map(str::to_string)
        .collect();
    let seg = |s: &str| s.split("::").map(str::to_string).collect::<Vec<_>>();
    assert_eq!(
        file_of(&files, &seg("a::b::Thing")).as_deref(),
        Some("a/b.rs")
    );
    assert_eq!(
        file_of(&files, &seg("a::Dataset")).as_deref(),
        Some("a/mod.rs")
    );
    assert_eq!(file_of(&files, &seg("x")).as_deref(), Some("lib.rs"));
    let found = paths_after("use crate::a::{b::X, c, Y};", "crate::");
    assert!(found.contains(&seg("a::b")) && found.contains(&seg("a::c")));
    assert!(paths_after("use foo::crate::a;", "crate::").is_empty());
    assert_eq!(module_path("a/mod.rs"), seg("a"));
    assert_eq!(module_path("a/b.rs"), seg("a::b"));
}
