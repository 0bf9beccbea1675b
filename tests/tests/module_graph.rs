//! The module graphs (docs/design.md, "Module graph"): no import cycle among the modules of
//! any crate of the workspace, the core's leaf modules (`error`, `limits`) import nothing of
//! the core but other leaves, and the simulator does not depend on the tools crate.
//!
//! A module is a file of a crate's `src/`: `nn/linear.rs` is `nn::linear`, `nn/mod.rs` is
//! `nn`, `lib.rs` (or a `main.rs` without one) the crate root; a `main.rs` beside a `lib.rs`
//! is a binary that names the library from outside. Its edges are the paths of its code that
//! name another module of its crate: `crate::`, `super::` and `self::` paths and paths through
//! a child module (`use linear::Input` in `nn/mod.rs`), in `use` lines, re-exports and inline,
//! with `{a, b::c}` groups expanded. A path names the longest module it starts with
//! (`crate::nn::linear::Input` is `nn::linear`, `crate::nn::Input` is `nn`, whose re-exports
//! are its own edges). Comments, literals and `#[cfg(test)]` items are left out, and so are
//! the files of `#[cfg(test)] mod name;`.
//!
//! The crates the workspace leaves out are not read: the fuzz targets are one file each (with
//! one shared body file), and the firmware's board module is one of three files picked per
//! target by `#[cfg_attr(..., path)]`, whose start-up code calls the image's `firmware_main`
//! back (the entry point of a freestanding binary).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Modules of the core that must not depend on any module outside this list.
const LEAVES: [&str; 2] = ["error", "limits"];

/// A module's path inside its crate (empty for the crate root).
type Module = Vec<String>;
/// Each module's name and the names of the modules it imports.
type Graph = BTreeMap<String, BTreeSet<String>>;

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The folders of the workspace's members that have a `src/` folder (the integration tests
/// are one file each).
fn crate_dirs() -> Vec<PathBuf> {
    let root = workspace_root();
    let manifest = read(&root.join("Cargo.toml"));
    quoted_list(&manifest, "members")
        .into_iter()
        .map(|dir| root.join(dir))
        .filter(|dir| dir.join("src").is_dir())
        .collect()
}

/// The quoted strings of the array `key = [...]` of a manifest.
fn quoted_list(manifest: &str, key: &str) -> Vec<String> {
    let start = manifest
        .find(&format!("{key} = ["))
        .unwrap_or_else(|| panic!("no `{key}` in the workspace manifest"));
    let list = &manifest[start..];
    let list = &list[..list.find(']').expect("a closed array")];
    list.split('"')
        .skip(1)
        .step_by(2)
        .map(String::from)
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("a readable source folder") {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The module a file of `src` holds; `None` for a `main.rs` beside a `lib.rs`.
fn module_of(src: &Path, file: &Path) -> Option<Module> {
    let relative = file.strip_prefix(src).expect("a file under src");
    let mut module: Module = relative
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    let file_name = module.pop().expect("a file name");
    match file_name.as_str() {
        "mod.rs" => {}
        "lib.rs" if module.is_empty() => {}
        "main.rs" if module.is_empty() => {
            if src.join("lib.rs").exists() {
                return None;
            }
        }
        name => module.push(name.trim_end_matches(".rs").to_string()),
    }
    Some(module)
}

fn display(module: &Module) -> String {
    if module.is_empty() {
        "crate".to_string()
    } else {
        module.join("::")
    }
}

/// `text` with its comments gone and its string and character literals emptied (`""`,
/// `''`); lifetimes stay.
fn without_comments_and_literals(text: &str) -> String {
    let c: Vec<char> = text.chars().collect();
    let at = |i: usize| c.get(i).copied().unwrap_or('\0');
    let is_ident = |ch: char| ch.is_alphanumeric() || ch == '_';
    let mut out = String::new();
    let mut i = 0;
    while i < c.len() {
        match (c[i], at(i + 1)) {
            ('/', '/') => {
                while i < c.len() && c[i] != '\n' {
                    i += 1;
                }
            }
            ('/', '*') => {
                let mut depth = 0;
                loop {
                    match (at(i), at(i + 1)) {
                        ('/', '*') => (depth, i) = (depth + 1, i + 2),
                        ('*', '/') => (depth, i) = (depth - 1, i + 2),
                        ('\0', _) => break,
                        _ => i += 1,
                    }
                    if depth == 0 {
                        break;
                    }
                }
            }
            ('"', _) => {
                i += 1;
                while i < c.len() && c[i] != '"' {
                    i += if c[i] == '\\' { 2 } else { 1 };
                }
                i += 1;
                out.push_str("\"\"");
            }
            ('r', '"' | '#') if !is_ident(at(i.wrapping_sub(1))) => {
                let hashes = (i + 1..).take_while(|&j| at(j) == '#').count();
                if at(i + 1 + hashes) != '"' {
                    out.push('r');
                    i += 1;
                    continue;
                }
                let closing: String = std::iter::once('"')
                    .chain("#".repeat(hashes).chars())
                    .collect();
                let body: String = c[i + 2 + hashes..].iter().collect();
                let len = body
                    .find(&closing)
                    .map_or(body.len(), |end| end + closing.len());
                i += 2 + hashes + body[..len].chars().count();
                out.push_str("\"\"");
            }
            ('\'', '\\') => {
                i += 3;
                while i < c.len() && c[i] != '\'' {
                    i += 1;
                }
                i += 1;
                out.push_str("''");
            }
            ('\'', _) if at(i + 2) == '\'' => {
                i += 3;
                out.push_str("''");
            }
            (ch, _) => {
                out.push(ch);
                i += 1;
            }
        }
    }
    out
}

/// `code` (without comments and literals) without its `#[cfg(test)]` items, and the names of
/// the modules that `#[cfg(test)] mod name;` declares (files of test code).
fn without_test_items(code: &str) -> (String, Vec<String>) {
    const TEST_ONLY: &str = "#[cfg(test)]";
    let (mut out, mut test_modules, mut from) = (String::new(), Vec::new(), 0);
    while let Some(found) = code[from..].find(TEST_ONLY) {
        let attribute = from + found;
        let item = after_attributes(code, attribute + TEST_ONLY.len());
        let end = item_end(code, item);
        if let Some(name) = declared_file_module(&code[item..end]) {
            test_modules.push(name);
        }
        out.push_str(&code[from..attribute]);
        from = end;
    }
    out.push_str(&code[from..]);
    (out, test_modules)
}

/// The index of the first item character at or after `at`, past spaces and attributes.
fn after_attributes(code: &str, mut at: usize) -> usize {
    loop {
        at += code[at..].len() - code[at..].trim_start().len();
        if !code[at..].starts_with("#[") {
            return at;
        }
        at = closing(code, at + 1, '[', ']');
    }
}

/// The index just after the bracket that closes the one at `open`.
fn closing(code: &str, open: usize, left: char, right: char) -> usize {
    let mut depth = 0;
    for (i, ch) in code[open..].char_indices() {
        if ch == left {
            depth += 1;
        } else if ch == right {
            depth -= 1;
            if depth == 0 {
                return open + i + 1;
            }
        }
    }
    code.len()
}

/// The index just after the item that starts at `start`: its `;` or its `{ ... }` block.
fn item_end(code: &str, start: usize) -> usize {
    let mut depth = 0;
    for (i, ch) in code[start..].char_indices() {
        match ch {
            '(' | '[' => depth += 1,
            ')' | ']' => depth -= 1,
            ';' if depth == 0 => return start + i + 1,
            '{' if depth == 0 => return closing(code, start + i, '{', '}'),
            _ => {}
        }
    }
    code.len()
}

/// `name` for an item `mod name;` (with any visibility).
fn declared_file_module(item: &str) -> Option<String> {
    let declaration = item.trim().strip_suffix(';')?;
    let (_, name) = declaration.split_once("mod ")?;
    let name = name.trim();
    name.chars()
        .all(|ch| ch.is_alphanumeric() || ch == '_')
        .then(|| name.to_string())
}

fn is_ident(token: &str) -> bool {
    let mut chars = token.chars();
    chars
        .next()
        .is_some_and(|c| c.is_alphabetic() || c == '_' || c == '$')
        && chars.all(|c| c.is_alphanumeric() || c == '_')
}

/// The tokens paths are made of: identifiers (`$crate` too), numbers, `::` and each other
/// character that is not a space.
fn tokens(code: &str) -> Vec<String> {
    let mut tokens = Vec::new();
    let mut rest = code;
    while let Some(ch) = rest.chars().next() {
        let head = ch.len_utf8();
        let len = if ch.is_alphanumeric() || ch == '_' || ch == '$' {
            head + rest[head..]
                .find(|c: char| !(c.is_alphanumeric() || c == '_'))
                .unwrap_or(rest.len() - head)
        } else if rest.starts_with("::") {
            2
        } else {
            head
        };
        if !ch.is_whitespace() {
            tokens.push(rest[..len].to_string());
        }
        rest = &rest[len..];
    }
    tokens
}

/// Every path of `code` that starts at an identifier followed by `::` (not `::std`, not the
/// middle of a path), as its segments, `use` groups expanded (`a::{b, c::d}` is `a::b` and
/// `a::c::d`).
fn paths(code: &str) -> Vec<Vec<String>> {
    let tokens = tokens(code);
    let mut found = Vec::new();
    let mut i = 0;
    while i + 1 < tokens.len() {
        let starts =
            is_ident(&tokens[i]) && tokens[i + 1] == "::" && (i == 0 || tokens[i - 1] != "::");
        i = if starts {
            use_tree(&tokens, i, Vec::new(), &mut found)
        } else {
            i + 1
        };
    }
    found
}

/// Reads the path or `use` tree at `tokens[i..]`, after the segments `prefix`, into `found`;
/// returns the index after it.
fn use_tree(
    tokens: &[String],
    mut i: usize,
    mut prefix: Vec<String>,
    found: &mut Vec<Vec<String>>,
) -> usize {
    loop {
        match tokens.get(i).map(String::as_str) {
            Some("{") => {
                i += 1;
                while let Some(token) = tokens.get(i) {
                    match token.as_str() {
                        "}" => return i + 1,
                        "," => i += 1,
                        _ => i = use_tree(tokens, i, prefix.clone(), found).max(i + 1),
                    }
                }
                return i;
            }
            Some(token) if is_ident(token) || token == "*" => {
                prefix.push(token.to_string());
                i += 1;
                if tokens.get(i).map(String::as_str) != Some("::") {
                    found.push(prefix);
                    return i;
                }
                i += 1;
            }
            _ => {
                found.push(prefix);
                return i;
            }
        }
    }
}

/// The module of `modules` that `path`, written in `module`, names: the longest module it
/// starts with; `None` for a path outside the crate.
fn named_module(modules: &BTreeSet<Module>, module: &Module, path: &[String]) -> Option<Module> {
    let child = |name: &str| [module.as_slice(), &[name.to_string()]].concat();
    let (mut named, rest) = match path.first()?.as_str() {
        "crate" | "$crate" => (Vec::new(), &path[1..]),
        "self" => (module.clone(), &path[1..]),
        "super" => {
            let supers = path.iter().take_while(|s| *s == "super").count();
            let kept = module.len().checked_sub(supers)?;
            (module[..kept].to_vec(), &path[supers..])
        }
        name if modules.contains(&child(name)) => (module.clone(), path),
        _ => return None,
    };
    for segment in rest.iter().filter(|s| *s != "self") {
        named.push(segment.clone());
        if !modules.contains(&named) {
            named.pop();
            break;
        }
    }
    Some(named)
}

/// The module graph of the crate in `crate_dir`.
fn module_graph(crate_dir: &Path) -> Graph {
    let src = crate_dir.join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut code = BTreeMap::new();
    let mut test_only = Vec::new();
    for file in files {
        let Some(module) = module_of(&src, &file) else {
            continue;
        };
        let (text, test_modules) = without_test_items(&without_comments_and_literals(&read(&file)));
        test_only.extend(
            test_modules
                .iter()
                .map(|name| [module.as_slice(), std::slice::from_ref(name)].concat()),
        );
        code.insert(module, text);
    }
    code.retain(|module, _| !test_only.iter().any(|test| module.starts_with(test)));
    let modules: BTreeSet<Module> = code.keys().cloned().collect();
    code.iter()
        .map(|(module, text)| {
            let imports = paths(text)
                .iter()
                .filter_map(|path| named_module(&modules, module, path))
                .filter(|named| named != module)
                .map(|named| display(&named))
                .collect();
            (display(module), imports)
        })
        .collect()
}

fn core_graph() -> Graph {
    module_graph(&workspace_root().join("core"))
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
fn no_crate_has_an_import_cycle() {
    let mut cycles = Vec::new();
    let mut sizes = Vec::new();
    for dir in crate_dirs() {
        let name = dir
            .file_name()
            .expect("a crate folder")
            .to_string_lossy()
            .into_owned();
        let graph = module_graph(&dir);
        if let Some(cycle) = find_cycle(&graph) {
            cycles.push(format!("{name}: {}", cycle.join(" -> ")));
        }
        sizes.push((name, graph.len()));
    }
    for (name, least) in [("core", 30), ("blobs", 5), ("host-sim", 20), ("tools", 4)] {
        assert!(
            sizes
                .iter()
                .any(|(crate_name, modules)| crate_name == name && *modules >= least),
            "read the modules of {name}: {sizes:?}"
        );
    }
    assert!(cycles.is_empty(), "import cycles:\n{}", cycles.join("\n"));
}

#[test]
fn the_graph_sees_top_level_and_file_level_edges() {
    let graph = core_graph();
    assert!(
        graph["localizer"].contains("matcher"),
        "`use crate::` edges"
    );
    assert!(
        graph["nn::residual"].contains("nn::linear"),
        "`use super::` edges"
    );
    assert!(graph["nn"].contains("nn::linear"), "re-exports of a child");
    assert!(
        graph["crate"].contains("localizer"),
        "re-exports of the root"
    );
}

#[test]
fn leaf_modules_import_only_leaves() {
    let graph = core_graph();
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
    let mut graph = core_graph();
    graph
        .get_mut("error")
        .expect("error module")
        .insert("localizer".to_string());
    let cycle = find_cycle(&graph).expect("error -> localizer -> error is a cycle");
    assert_eq!(cycle.first(), cycle.last());
    assert!(cycle.contains(&"error".to_string()));
}

#[test]
fn paths_are_resolved_with_groups_and_without_comments_literals_or_tests() {
    let modules: BTreeSet<Module> = [
        "",
        "camera",
        "map",
        "pose",
        "rng",
        "nn",
        "nn::linear",
        "nn::norm",
    ]
    .iter()
    .map(|name| {
        name.split("::")
            .filter(|s| !s.is_empty())
            .map(String::from)
            .collect()
    })
    .collect();
    let code = "use crate::{camera::Camera, nn::{self, norm}};\n\
        use super::linear::Input; // crate::map\n\
        let x = self::Local::new(\"crate::rng\", '\"', b'{'); /* crate::rng */\n\
        fn f<'a>(x: &'a str) -> crate::pose::Pose { todo!() }\n\
        #[cfg(test)]\n#[allow(unused)]\nfn helper() { crate::rng::next(); }\n\
        #[cfg(test)]\nmod tests { use crate::map; }";
    let (code, test_modules) = without_test_items(&without_comments_and_literals(code));
    assert!(test_modules.is_empty());
    let module: Module = vec!["nn".into(), "norm".into()];
    let named: BTreeSet<String> = paths(&code)
        .iter()
        .filter_map(|path| named_module(&modules, &module, path))
        .map(|named| display(&named))
        .collect();
    assert_eq!(
        named.into_iter().collect::<Vec<_>>(),
        ["camera", "nn", "nn::linear", "nn::norm", "pose"]
    );
    let (_, test_modules) = without_test_items("mod a;\n#[cfg(test)]\npub(crate) mod fixtures;");
    assert_eq!(test_modules, ["fixtures"]);
}

#[test]
fn the_simulator_does_not_depend_on_the_tools() {
    let manifest = read(&workspace_root().join("host-sim/Cargo.toml"));
    assert!(
        !manifest.contains("gomatch-tools"),
        "host-sim/Cargo.toml names gomatch-tools"
    );
}
