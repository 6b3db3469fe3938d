//! The front door stays true: every relative link of the README and the docs book resolves
//! to a file of the repository, and every figure the README's results table states is found
//! in the committed results files under `docs/` (outside the book, which is prose).

mod common;

use common::root;
use std::path::{Path, PathBuf};

/// Markdown files of the README and the book.
fn markdown_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, files: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(&path, files);
            } else if path.extension().is_some_and(|e| e == "md") {
                files.push(path);
            }
        }
    }
    let mut files = vec![root().join("README.md")];
    walk(&root().join("docs/book/src"), &mut files);
    files
}

/// The targets of the inline links and images `[..](target)` of a markdown text, outside
/// code blocks and code spans.
fn link_targets(text: &str) -> Vec<String> {
    let mut targets = Vec::new();
    let mut in_block = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if in_block {
            continue;
        }
        // Code spans hold examples, not links.
        let prose: String = line.split('`').step_by(2).collect::<Vec<_>>().join(" ");
        let mut rest = prose.as_str();
        while let Some(start) = rest.find("](") {
            let after = &rest[start + 2..];
            let Some(end) = after.find(')') else { break };
            targets.push(after[..end].to_string());
            rest = &after[end..];
        }
    }
    targets
}

#[test]
fn every_relative_link_of_the_readme_and_the_book_resolves() {
    let mut broken = Vec::new();
    for file in markdown_files() {
        let text = std::fs::read_to_string(&file).unwrap();
        for target in link_targets(&text) {
            if target.contains("://") || target.starts_with('#') || target.starts_with("mailto:") {
                continue;
            }
            let path = target.split('#').next().unwrap();
            let resolved = file.parent().unwrap().join(path);
            if !resolved.exists() {
                broken.push(format!("{}: {target}", file.display()));
            }
        }
    }
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

/// The decimal figures (`34.06`, `0.450`) of a text.
fn figures(text: &str) -> Vec<String> {
    let mut found = Vec::new();
    let chars: Vec<char> = text.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        if chars[i].is_ascii_digit() && (i == 0 || !chars[i - 1].is_ascii_alphanumeric()) {
            let start = i;
            while i < chars.len() && (chars[i].is_ascii_digit() || chars[i] == '.') {
                i += 1;
            }
            let number: String = chars[start..i].iter().collect::<String>();
            let number = number.trim_end_matches('.');
            let followed_by_word =
                i < chars.len() && chars[i].is_ascii_alphabetic() && chars[i] != 'x';
            if number.contains('.') && !followed_by_word {
                found.push(number.to_string());
            }
        } else {
            i += 1;
        }
    }
    found
}

#[test]
fn every_figure_of_the_readme_results_is_in_the_committed_results() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let results = readme
        .split("\n## Results\n")
        .nth(1)
        .expect("the README has a Results section")
        .split("\n## ")
        .next()
        .unwrap();
    // Every committed results file under docs/, the book's prose left out.
    fn walk(dir: &Path, text: &mut String) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                if !path.ends_with("book") {
                    walk(&path, text);
                }
            } else if let Ok(content) = std::fs::read_to_string(&path) {
                text.push_str(&content);
            }
        }
    }
    let mut committed = String::new();
    walk(&root().join("docs"), &mut committed);
    let figures = figures(results);
    assert!(!figures.is_empty(), "no figure in the results section");
    let missing: Vec<&String> = figures
        .iter()
        .filter(|f| !committed.contains(f.as_str()))
        .collect();
    assert!(
        missing.is_empty(),
        "README figures not found in the committed results under docs/: {missing:?}"
    );
}

#[test]
fn the_readme_is_a_front_door() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(
        lines <= 260,
        "README.md has {lines} lines; the book holds the rest"
    );
}

/// Every test the README's "Hard cases" table names (in backticks, in its last column) is a
/// test of `tests/hard_cases.rs`.
#[test]
fn every_test_the_readme_hard_cases_table_names_exists() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let suite = std::fs::read_to_string(root().join("tests/hard_cases.rs")).unwrap();
    let section = readme
        .split("## Hard cases")
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .expect("README has a Hard cases section");
    let named: Vec<&str> = (section.lines())
        .filter(|line| line.starts_with("| ") && !line.starts_with("| ---"))
        .filter_map(|line| line.trim_end_matches('|').rsplit('|').next())
        .flat_map(|outcome| outcome.split('`').skip(1).step_by(2))
        .filter(|name| name.contains('_'))
        .filter(|name| name.chars().all(|c| c.is_ascii_lowercase() || c == '_'))
        .collect();
    assert!(named.len() >= 8, "{named:?}");
    for name in named {
        assert!(
            suite.contains(&format!("fn {name}(")),
            "README names `{name}`, which is not a test of tests/hard_cases.rs"
        );
    }
}
