//! The core's top-level modules form a layered graph without import cycles: each stage of the
//! paper (front-end, GPE, back-end) builds on the layers below it (geometry, storage, graph,
//! solver, sensor) and never the other way round, so a layer can be read, tested and replaced
//! without the ones above it.
//!
//! The check reads the sources, not the compiler's view. A module `a` depends on `b` when a
//! non-test, non-comment line of a file under `src/a` (or `src/a.rs`) names `crate::b`. Test
//! code is left out: a test may build on anything.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

type Graph = BTreeMap<String, BTreeSet<String>>;

/// The top-level modules declared in `lib.rs`.
fn top_modules(src: &Path) -> BTreeSet<String> {
    let lib = fs::read_to_string(src.join("lib.rs")).expect("read lib.rs");
    lib.lines()
        .map(str::trim)
        .filter_map(|l| {
            let l = l.strip_prefix("pub ").unwrap_or(l);
            let name = l.strip_prefix("mod ")?.strip_suffix(';')?;
            Some(name.trim().to_string())
        })
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = fs::read_dir(dir)
        .expect("read dir")
        .map(|e| e.expect("dir entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

/// The source lines of a file that are compiled outside tests, without comments.
fn library_lines(text: &str) -> Vec<&str> {
    let mut lines = Vec::new();
    let mut cfg_test = false;
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            cfg_test = true;
            continue;
        }
        // Everything after a `#[cfg(test)] mod ...` is the file's test module, which the
        // project keeps at the end of a file.
        if cfg_test && (t.starts_with("mod ") || t.starts_with("pub mod ")) {
            break;
        }
        cfg_test = false;
        if t.starts_with("//") {
            continue;
        }
        lines.push(line.split("//").next().unwrap_or(""));
    }
    lines
}

/// The top-level modules named as `crate::NAME` in `line`.
fn crate_paths<'a>(line: &'a str, modules: &BTreeSet<String>) -> Vec<&'a str> {
    let mut found = Vec::new();
    let mut rest = line;
    while let Some(i) = rest.find("crate::") {
        let preceded_by_dollar = rest[..i].ends_with('$');
        let tail = &rest[i + "crate::".len()..];
        let end = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        let name = &tail[..end];
        if !preceded_by_dollar && modules.contains(name) {
            found.push(name);
        }
        rest = tail;
    }
    found
}

/// The module graph of the crate rooted at `src`.
fn module_graph(src: &Path) -> Graph {
    let modules = top_modules(src);
    let mut graph: Graph = modules
        .iter()
        .map(|m| (m.clone(), BTreeSet::new()))
        .collect();
    let mut files = Vec::new();
    rust_files(src, &mut files);
    for file in files {
        let rel = file.strip_prefix(src).expect("under src");
        let first = rel.components().next().expect("a component");
        let owner = first
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if !modules.contains(&owner) {
            continue; // lib.rs itself
        }
        let name = rel.file_name().map(|n| n.to_string_lossy().to_string());
        if matches!(name.as_deref(), Some("tests.rs" | "proptests.rs")) {
            continue;
        }
        let text = fs::read_to_string(&file).expect("read source");
        for line in library_lines(&text) {
            for dep in crate_paths(line, &modules) {
                if dep != owner {
                    graph
                        .entry(owner.clone())
                        .or_default()
                        .insert(dep.to_string());
                }
            }
        }
    }
    graph
}

/// One cycle of `graph` as the list of its modules, if there is any.
fn find_cycle(graph: &Graph) -> Option<Vec<String>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Open,
        Done,
    }
    fn visit(
        node: &str,
        graph: &Graph,
        marks: &mut BTreeMap<String, Mark>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        marks.insert(node.to_string(), Mark::Open);
        stack.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            match marks.get(next.as_str()).copied().unwrap_or(Mark::New) {
                Mark::Open => {
                    let start = stack.iter().position(|s| s == next).expect("on the stack");
                    let mut cycle = stack[start..].to_vec();
                    cycle.push(next.clone());
                    return Some(cycle);
                }
                Mark::New => {
                    if let Some(c) = visit(next, graph, marks, stack) {
                        return Some(c);
                    }
                }
                Mark::Done => {}
            }
        }
        stack.pop();
        marks.insert(node.to_string(), Mark::Done);
        None
    }
    let mut marks = BTreeMap::new();
    for node in graph.keys() {
        if marks.get(node.as_str()).copied().unwrap_or(Mark::New) == Mark::New {
            if let Some(c) = visit(node, graph, &mut marks, &mut Vec::new()) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn the_core_modules_have_no_import_cycle() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let graph = module_graph(&src);
    // The check must see the stages at all: the mapper builds on the front-end and the GPE.
    assert!(graph["mapper"].contains("frontend"), "graph: {graph:?}");
    assert!(graph["mapper"].contains("gpe"), "graph: {graph:?}");
    if let Some(cycle) = find_cycle(&graph) {
        panic!("import cycle between core modules: {}", cycle.join(" -> "));
    }
}

#[test]
fn the_cycle_finder_finds_cycles_and_only_cycles() {
    let g = |edges: &[(&str, &str)]| {
        let mut graph = Graph::new();
        for (a, b) in edges {
            graph
                .entry(a.to_string())
                .or_default()
                .insert(b.to_string());
            graph.entry(b.to_string()).or_default();
        }
        graph
    };
    assert_eq!(find_cycle(&g(&[("a", "b"), ("b", "c"), ("a", "c")])), None);
    let cycle = find_cycle(&g(&[("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")]))
        .expect("a -> b -> c -> a");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4);
    assert!(find_cycle(&g(&[("x", "y"), ("y", "x")])).is_some());
}

#[test]
fn the_source_reader_skips_comments_tests_and_macro_paths() {
    let modules: BTreeSet<String> = ["geom", "solver"].iter().map(|s| s.to_string()).collect();
    let text = "use crate::geom::Se2;\n/// see [`crate::solver`]\nlet x = $crate::solver::f();\n\
                #[cfg(test)]\nmod tests {\n    use crate::solver::g;\n}\n";
    let found: Vec<&str> = library_lines(text)
        .into_iter()
        .flat_map(|l| crate_paths(l, &modules))
        .collect();
    assert_eq!(found, vec!["geom"]);
}
