//! The core's module graph (docs/design.md, "Module graph"): no import cycle between its
//! top-level modules, and the leaf modules (`error`, `limits`) import nothing of the crate
//! but other leaves. Edges are the `crate::<module>` paths of each module's non-test code
//! (`use` lines, re-exports and inline paths; comments and `#[cfg(test)] mod tests` are
//! left out, the latter always closes its file).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Modules that must not depend on any module outside this list.
const LEAVES: [&str; 2] = ["error", "limits"];

type Graph = BTreeMap<String, BTreeSet<String>>;

fn core_src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../core/src")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("core/src is readable") {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The top-level module a file of `core/src` belongs to (`nn/linear.rs` -> `nn`).
fn module_of(src: &Path, file: &Path) -> String {
    let relative = file.strip_prefix(src).expect("file under core/src");
    let first = relative.components().next().expect("non-empty path");
    let name = first.as_os_str().to_string_lossy();
    name.trim_end_matches(".rs").to_string()
}

/// The code of a file without comments and without its trailing test module.
fn non_test_code(text: &str) -> String {
    let code = match text.find("#[cfg(test)]\nmod tests") {
        Some(at) => &text[..at],
        None => text,
    };
    code.lines()
        .map(|line| match line.find("//") {
            Some(at) => &line[..at],
            None => line,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Modules named by `crate::<name>` in `code`, with `crate::{a, b::c}` groups expanded.
fn referenced_modules(code: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    let is_ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    for (at, _) in code.match_indices("crate::") {
        let rest = &code[at + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let body = &group[..group.find('}').unwrap_or(group.len())];
            for item in body.split(',') {
                let name: String = item.trim().chars().take_while(|&c| is_ident(c)).collect();
                found.insert(name);
            }
        } else {
            found.insert(rest.chars().take_while(|&c| is_ident(c)).collect());
        }
    }
    found
}

fn module_graph() -> Graph {
    let src = core_src();
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut graph = Graph::new();
    for file in &files {
        let module = module_of(&src, file);
        let text = std::fs::read_to_string(file).expect("readable source");
        graph.entry(module.clone()).or_default();
        let deps = referenced_modules(&non_test_code(&text));
        graph.get_mut(&module).expect("inserted").extend(deps);
    }
    let modules: BTreeSet<String> = graph.keys().cloned().collect();
    for (module, deps) in graph.iter_mut() {
        deps.retain(|d| d != module && modules.contains(d) && d != "lib");
    }
    graph.remove("lib");
    graph
}

/// A cycle of the graph, if it has one (depth-first search with colours).
fn find_cycle(graph: &Graph) -> Option<Vec<String>> {
    fn visit(
        graph: &Graph,
        node: &str,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(start) = path.iter().position(|n| n == node) {
            let mut cycle = path[start..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(graph, next, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_string());
        None
    }
    let mut done = BTreeSet::new();
    graph
        .keys()
        .find_map(|node| visit(graph, node, &mut Vec::new(), &mut done))
}

#[test]
fn the_core_has_no_import_cycle() {
    let graph = module_graph();
    assert!(graph.len() > 15, "read the core's modules: {graph:?}");
    assert!(
        graph["localizer"].contains("matcher"),
        "the parser sees `use crate::` edges"
    );
    if let Some(cycle) = find_cycle(&graph) {
        panic!("import cycle in core/src: {}", cycle.join(" -> "));
    }
}

#[test]
fn leaf_modules_import_only_leaves() {
    let graph = module_graph();
    for leaf in LEAVES {
        let outside: Vec<_> = graph[leaf]
            .iter()
            .filter(|d| !LEAVES.contains(&d.as_str()))
            .collect();
        assert!(
            outside.is_empty(),
            "{leaf}.rs imports {outside:?}; it must stay a leaf"
        );
    }
}

#[test]
fn the_cycle_finder_finds_a_planted_cycle() {
    let mut graph = module_graph();
    graph
        .get_mut("error")
        .expect("error module")
        .insert("localizer".to_string());
    let cycle = find_cycle(&graph).expect("error -> localizer -> error is a cycle");
    assert_eq!(cycle.first(), cycle.last());
    assert!(cycle.contains(&"error".to_string()));
}

#[test]
fn crate_paths_are_parsed_with_groups_and_without_comments() {
    let code = non_test_code(
        "use crate::{camera::Camera, pose};\nlet x = crate::map::X; // crate::link\n#[cfg(test)]\nmod tests { use crate::rng; }",
    );
    let found: Vec<_> = referenced_modules(&code).into_iter().collect();
    assert_eq!(found, ["camera", "map", "pose"]);
}
