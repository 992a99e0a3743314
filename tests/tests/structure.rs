//! The crates' module structure: no module imports from a module that depends on it. Every
//! `crate::…` and `super::…` path in non-test code is resolved to the module it names, the edge
//! is lifted to the two sibling modules under their closest common parent, and each parent's
//! sibling graph must be acyclic. (A child using its own parent's items is not a sibling edge.)

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

type Module = Vec<String>;

/// Every `.rs` file of `src` (binaries excluded) with its module path.
fn modules(src: &Path) -> Vec<(Module, PathBuf)> {
    let mut out = Vec::new();
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("read src") {
            let path = entry.expect("entry").path();
            let rel = path.strip_prefix(src).expect("under src");
            if rel.starts_with("bin") {
                continue;
            }
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let mut module: Module = rel
                .with_extension("")
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            if matches!(module.last().map(String::as_str), Some("mod" | "lib")) {
                module.pop();
            }
            out.push((module, path));
        }
    }
    out
}

/// Paths after `prefix` (`crate::` or `super::`) in `code`, each as its segments.
fn paths_after(code: &str, prefix: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(at) = rest.find(prefix) {
        let before = rest[..at].chars().last();
        rest = &rest[at + prefix.len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let end = rest
            .find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
            .unwrap_or(rest.len());
        out.push(
            rest[..end]
                .split("::")
                .filter(|s| !s.is_empty())
                .map(str::to_owned)
                .collect(),
        );
    }
    out
}

/// Whether the module in `path` is declared for tests only (`#[cfg(test)]` on the line before
/// its `mod` in its parent): then all of it is test code, as what follows `#[cfg(test)]` in a
/// file is.
fn test_only(path: &Path) -> bool {
    let own = if path.file_name().is_some_and(|f| f == "mod.rs") {
        path.parent()
    } else {
        Some(path)
    };
    let Some((name, dir)) = own.and_then(|p| Some((p.file_stem()?.to_str()?, p.parent()?))) else {
        return false;
    };
    if name == "lib" {
        return false;
    }
    let parent = ["mod.rs", "lib.rs"]
        .iter()
        .map(|f| dir.join(f))
        .find(|p| p.exists())
        .unwrap_or_else(|| dir.with_extension("rs"));
    let text = std::fs::read_to_string(parent).unwrap_or_default();
    let lines: Vec<&str> = text.lines().map(str::trim).collect();
    let declaration = format!("mod {name};");
    lines
        .windows(2)
        .any(|w| w[0] == "#[cfg(test)]" && w[1].ends_with(&declaration))
}

/// `text` without the items under `#[cfg(test)]`: each from the attribute to its `;` or to the
/// brace closing its block (braces in string and character literals skipped), so that code after
/// a test module still counts. An item left open runs to the end of the file.
fn without_test_items(text: &str) -> String {
    const MARK: &str = "#[cfg(test)]";
    let mut out = String::new();
    let mut rest = text;
    while let Some(at) = rest.find(MARK) {
        out.push_str(&rest[..at]);
        let item = &rest[at + MARK.len()..];
        rest = item_end(item).map_or("", |end| &item[end..]);
    }
    out.push_str(rest);
    out
}

/// The byte just past the item that starts `item`: its `;` at depth 0, or its block's closing
/// brace; `None` when it never closes.
fn item_end(item: &str) -> Option<usize> {
    let bytes = item.as_bytes();
    let (mut depth, mut i) = (0usize, 0);
    while i < bytes.len() {
        match bytes[i] {
            b'"' => {
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    i += if bytes[i] == b'\\' { 2 } else { 1 };
                }
            }
            b'\'' if bytes.get(i + 2) == Some(&b'\'') => i += 2,
            b'{' => depth += 1,
            b'}' => {
                depth = depth.checked_sub(1)?;
                if depth == 0 {
                    return Some(i + 1);
                }
            }
            b';' if depth == 0 => return Some(i + 1),
            _ => {}
        }
        i += 1;
    }
    None
}

/// The sibling edges (parent, from child, to child) of a crate's non-test code.
fn sibling_edges(src: &Path) -> BTreeSet<(Module, String, String)> {
    let files = modules(src);
    let known: BTreeSet<Module> = files.iter().map(|(m, _)| m.clone()).collect();
    let mut edges = BTreeSet::new();
    for (module, path) in &files {
        if test_only(path) {
            continue;
        }
        let text = std::fs::read_to_string(path).expect("read");
        // Non-test code without comments (a doc link is not a dependency).
        let code: String = without_test_items(&text)
            .lines()
            .map(|l| l.split("//").next().unwrap_or(""))
            .collect::<Vec<_>>()
            .join("\n");
        let is_dir_module = path.file_name().is_some_and(|f| f == "mod.rs" || f == "lib.rs");
        let parent: Module = if is_dir_module {
            module
                .iter()
                .take(module.len().saturating_sub(1))
                .cloned()
                .collect()
        } else {
            module[..module.len() - 1].to_vec()
        };
        let targets = paths_after(&code, "crate::").into_iter().chain(
            paths_after(&code, "super::")
                .into_iter()
                .map(|p| parent.iter().cloned().chain(p).collect::<Module>()),
        );
        for target in targets {
            let named = (0..=target.len())
                .rev()
                .map(|n| target[..n].to_vec())
                .find(|m| known.contains(m))
                .unwrap_or_default();
            let common = module.iter().zip(&named).take_while(|(a, b)| a == b).count();
            if common < module.len() && common < named.len() {
                edges.insert((
                    module[..common].to_vec(),
                    module[common].clone(),
                    named[common].clone(),
                ));
            }
        }
    }
    edges
}

/// A cycle among siblings, if any, as the modules on it.
fn cycle(edges: &BTreeSet<(Module, String, String)>) -> Option<(Module, Vec<String>)> {
    let mut graphs: BTreeMap<&Module, BTreeMap<&str, Vec<&str>>> = BTreeMap::new();
    for (parent, from, to) in edges {
        graphs
            .entry(parent)
            .or_default()
            .entry(from)
            .or_default()
            .push(to);
    }
    for (parent, graph) in graphs {
        // Depth-first search with the path kept: a node met again on the path closes a cycle.
        fn visit<'a>(
            node: &'a str,
            graph: &BTreeMap<&'a str, Vec<&'a str>>,
            path: &mut Vec<&'a str>,
            done: &mut BTreeSet<&'a str>,
        ) -> Option<Vec<String>> {
            if let Some(at) = path.iter().position(|n| *n == node) {
                return Some(
                    path[at..]
                        .iter()
                        .map(|s| s.to_string())
                        .chain([node.to_owned()])
                        .collect(),
                );
            }
            if !done.insert(node) {
                return None;
            }
            path.push(node);
            for next in graph.get(node).into_iter().flatten() {
                if let Some(c) = visit(next, graph, path, done) {
                    return Some(c);
                }
            }
            path.pop();
            None
        }
        let mut done = BTreeSet::new();
        for start in graph.keys() {
            if let Some(c) = visit(start, &graph, &mut Vec::new(), &mut done) {
                return Some((parent.clone(), c));
            }
        }
    }
    None
}

fn crate_src(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(name)
        .join("src")
}

#[test]
fn no_module_of_any_crate_imports_from_a_module_that_depends_on_it() {
    for name in [
        "proto",
        "transport",
        "service",
        "client",
        "capi",
        "ros",
        "ros2",
        "sim",
        "lab",
    ] {
        let edges = sibling_edges(&crate_src(name));
        if let Some((parent, c)) = cycle(&edges) {
            panic!(
                "{name}: modules under {:?} form a cycle: {}",
                parent,
                c.join(" → ")
            );
        }
    }
}

#[test]
fn a_module_declared_for_tests_only_makes_no_cycle() {
    let tmp = rangegp_tests::TempDir::new("structure-tests").expect("temp dir");
    let dir = tmp.path();
    let src = dir.join("src");
    std::fs::create_dir_all(src.join("b")).expect("dirs");
    std::fs::write(
        src.join("lib.rs"),
        "pub mod a;\npub mod b;\n#[cfg(test)]\nmod support;\n",
    )
    .expect("lib");
    std::fs::write(src.join("a.rs"), "use crate::b::Thing;\n").expect("a");
    std::fs::write(
        src.join("b/mod.rs"),
        "pub struct Thing;\n#[cfg(test)]\nmod tests;\n",
    )
    .expect("b");
    std::fs::write(src.join("b/tests.rs"), "use crate::support::helper;\n").expect("tests");
    std::fs::write(src.join("support.rs"), "use crate::a::X;\n").expect("support");
    let edges = sibling_edges(&src);
    // Only a ← b: the test code's b → support → a is not the crate's.
    assert!(cycle(&edges).is_none(), "{edges:?}");
    assert_eq!(
        edges,
        BTreeSet::from([(Module::new(), "a".to_owned(), "b".to_owned())])
    );
}

#[test]
fn only_the_item_under_cfg_test_is_test_code() {
    let text = "use crate::a::A;\n#[cfg(test)]\nuse crate::t::T;\n#[cfg(test)]\nmod tests {\n    \
                use crate::u::U;\n    fn f() { let _ = format!(\"{{ }} {}\", '{'); }\n}\n\
                fn g() { let _ = crate::b::B; }\n";
    let code = without_test_items(text);
    assert!(
        code.contains("crate::a::A") && code.contains("crate::b::B"),
        "{code}"
    );
    assert!(!code.contains("crate::t") && !code.contains("crate::u"), "{code}");
    assert_eq!(
        without_test_items("fn f() {}\n#[cfg(test)]\nmod open {"),
        "fn f() {}\n"
    );
}

#[test]
fn the_check_finds_a_cycle_where_there_is_one() {
    let tmp = rangegp_tests::TempDir::new("structure").expect("temp dir");
    let dir = tmp.path();
    let src = dir.join("src");
    std::fs::create_dir_all(src.join("b")).expect("dirs");
    std::fs::write(src.join("lib.rs"), "pub mod a;\npub mod b;\n").expect("lib");
    std::fs::write(src.join("a.rs"), "use crate::b::inner::Thing;\n").expect("a");
    std::fs::write(src.join("b/mod.rs"), "pub mod inner;\n").expect("b");
    std::fs::write(
        src.join("b/inner.rs"),
        "pub struct Thing;\nfn f() { let _ = crate::a::X; }\n#[cfg(test)]\nuse crate::c;\n",
    )
    .expect("inner");
    let found = cycle(&sibling_edges(&src));
    let (parent, c) = found.expect("a ⇄ b is a cycle");
    assert!(parent.is_empty());
    assert!(
        c.contains(&"a".to_owned()) && c.contains(&"b".to_owned()),
        "{c:?}"
    );
}

/// `cargo tree` for one package of the workspace (offline, from the lock file), one name per line.
fn cargo_tree(package: &str, depth: Option<u32>) -> Vec<String> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(&root).args([
        "tree", "--frozen", "-e", "normal", "--prefix", "none", "-p", package,
    ]);
    if let Some(d) = depth {
        cmd.args(["--depth", &d.to_string()]);
    }
    let out = rangegp_tests::child::succeeded_within(&mut cmd, "cargo tree").expect("run cargo tree");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().next().map(str::to_owned))
        .collect()
}

#[test]
fn the_crate_edges_in_the_architecture_document_are_cargo_s() {
    let doc = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/ARCHITECTURE.md"))
        .expect("read ARCHITECTURE.md");
    let block = doc
        .split("```crate-edges\n")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .expect("a crate-edges block");
    let documented: BTreeMap<String, BTreeSet<String>> = block
        .lines()
        .filter_map(|l| l.split_once(" -> "))
        .map(|(from, to)| {
            (
                from.to_owned(),
                to.split_whitespace().map(str::to_owned).collect(),
            )
        })
        .collect();
    for package in [
        "proto",
        "transport",
        "sim",
        "client",
        "c",
        "service",
        "lab",
        "tests",
    ] {
        let name = format!("rangegp-{package}");
        let actual: BTreeSet<String> = cargo_tree(&name, Some(1))
            .into_iter()
            .filter(|d| d.starts_with("rangegp-") && *d != name)
            .collect();
        let listed = documented.get(&name).cloned().unwrap_or_default();
        assert_eq!(actual, listed, "{name}: cargo tree against docs/ARCHITECTURE.md");
    }
}

#[test]
fn the_daemon_links_no_lab_code_and_a_planner_no_simulator_or_pictures() {
    let forbidden = |package: &str, names: &[&str]| {
        let tree = cargo_tree(package, None);
        for name in names {
            assert!(!tree.iter().any(|d| d == name), "{package} depends on {name}");
        }
    };
    forbidden(
        "rangegp-service",
        &[
            "rangegp-sim",
            "rangegp-client",
            "image",
            "colorous",
            "indicatif",
            "plotters",
        ],
    );
    forbidden(
        "rangegp-client",
        &["rangegp-sim", "image", "colorous", "plotters"],
    );
    // The bridge runs on the robot beside the daemon: no daemon, simulator or lab inside it.
    forbidden(
        "rangegp-ros2",
        &["rangegp-service", "rangegp-sim", "rangegp-lab", "plotters"],
    );
}
