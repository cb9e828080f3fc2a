//! The documentation cannot drift from the code: every relative link in the README and
//! `docs/` resolves (file and heading), and every `nerf ...` line in their `sh` blocks
//! parses with the command line's own parser. Placeholders are written `<RUN>`,
//! `<MINUTES>` and so on, and stand for a value of their kind here.

use std::path::{Path, PathBuf};

use clap::Parser;

use crate::Cli;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The README and every Markdown file under `docs/`.
fn documents() -> Vec<PathBuf> {
    let root = workspace();
    let mut out = vec![root.join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/ exists")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    docs.sort();
    out.extend(docs);
    out
}

/// GitHub's anchor of a heading: lower case, spaces to `-`, punctuation dropped.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The lines of `text` outside fenced code blocks.
fn prose(text: &str) -> Vec<&str> {
    let mut fenced = false;
    text.lines()
        .filter(|l| {
            if l.trim_start().starts_with("```") {
                fenced = !fenced;
                return false;
            }
            !fenced
        })
        .collect()
}

fn anchors(text: &str) -> Vec<String> {
    prose(text)
        .into_iter()
        .filter_map(|l| l.strip_prefix('#'))
        .map(|l| anchor(l.trim_start_matches('#')))
        .collect()
}

/// `(target, line)` of every Markdown link `[..](target)` in prose.
fn links(text: &str) -> Vec<(String, usize)> {
    let mut out = Vec::new();
    let mut fenced = false;
    for (n, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        }
        if fenced {
            continue;
        }
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            let Some(end) = rest.find(')') else { break };
            out.push((rest[..end].to_string(), n + 1));
            rest = &rest[end..];
        }
    }
    out
}

#[test]
fn every_relative_link_resolves() {
    let mut broken = Vec::new();
    let mut checked = 0;
    for doc in documents() {
        let text = std::fs::read_to_string(&doc).expect("readable document");
        let dir = doc.parent().expect("a folder");
        for (target, line) in links(&text) {
            if target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let (file, fragment) = match target.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (target.as_str(), None),
            };
            let path = if file.is_empty() {
                doc.clone()
            } else {
                dir.join(file)
            };
            let name = format!("{}:{line}: {target}", doc.display());
            if !path.exists() {
                broken.push(format!("{name} (no such file)"));
                continue;
            }
            if let Some(fragment) = fragment {
                let linked = std::fs::read_to_string(&path).unwrap_or_default();
                if !anchors(&linked).iter().any(|a| a == fragment) {
                    broken.push(format!("{name} (no such heading)"));
                }
            }
        }
    }
    assert!(
        checked > 10,
        "found only {checked} links: is the parser broken?"
    );
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

/// A value of the kind a placeholder names.
fn substitute(word: &str) -> String {
    let mut out = word.to_string();
    for (placeholder, value) in [
        ("<MINUTES>", "10"),
        ("<STEPS>", "1000"),
        ("<SEED>", "1"),
        ("<N>", "4"),
        ("<WEIGHT>", "0.0001"),
    ] {
        out = out.replace(placeholder, value);
    }
    // Every other placeholder names a file or folder.
    while let (Some(a), Some(b)) = (out.find('<'), out.find('>')) {
        if b < a {
            break;
        }
        out.replace_range(a..=b, "x");
    }
    out
}

/// `(document, line, arguments)` of every `nerf` command in a fenced `sh` block.
fn documented_commands() -> Vec<(String, usize, Vec<String>)> {
    let mut out = Vec::new();
    for doc in documents() {
        let text = std::fs::read_to_string(&doc).expect("readable document");
        let mut in_sh = false;
        for (n, line) in text.lines().enumerate() {
            let t = line.trim();
            if t.starts_with("```") {
                in_sh = !in_sh && t == "```sh";
                continue;
            }
            if !in_sh || !t.starts_with("nerf ") {
                continue;
            }
            let command = t.split(" #").next().unwrap_or(t);
            let args = command.split_whitespace().map(substitute).collect();
            out.push((doc.display().to_string(), n + 1, args));
        }
    }
    out
}

#[test]
fn every_documented_command_parses() {
    let commands = documented_commands();
    assert!(
        commands.len() > 30,
        "found only {} documented commands",
        commands.len()
    );
    let failures: Vec<String> = commands
        .iter()
        .filter_map(|(doc, line, args)| {
            Cli::try_parse_from(args).err().map(|e| {
                let first = e.to_string().lines().next().unwrap_or("").to_string();
                format!("{doc}:{line}: {} -> {first}", args.join(" "))
            })
        })
        .collect();
    assert!(
        failures.is_empty(),
        "documented commands the CLI refuses:\n{}",
        failures.join("\n")
    );
}

#[test]
fn a_wrong_option_or_a_missing_file_is_caught() {
    assert!(Cli::try_parse_from(["nerf", "train", "--no-such-option"]).is_err());
    assert!(Cli::try_parse_from(["nerf", "train", "--data", "x"]).is_ok());
    assert_eq!(substitute("<RUN>/a"), "x/a");
    assert_eq!(substitute("--minutes=<MINUTES>"), "--minutes=10");
    let text = "see [a](b.md#c) and [d](#e-f)\n```sh\n[x](nope)\n```\n## E f\n";
    let found: Vec<String> = links(text).into_iter().map(|(t, _)| t).collect();
    assert_eq!(found, ["b.md#c", "#e-f"]);
    assert_eq!(anchors(text), ["e-f"]);
    assert_eq!(
        anchor("The viewer (fast model, lego_400 5000-step run)"),
        "the-viewer-fast-model-lego_400-5000-step-run"
    );
}
