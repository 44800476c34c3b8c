//! No import circle between the files of `crates/host/src` (issue 37 item 4): every file
//! stands above the files it names, so a layer can be read, tested and replaced without the
//! ones above it.
//!
//! The graph is built from the source text alone, so the same functions serve any crate:
//! [`file_graph`] takes a `src` directory and [`circles`] returns its strongly connected
//! components. An edge A -> B means A names a module that lives in file B through
//! `crate::…`, `super::…`, `self::…` or a child module's name (in a `use` or in an
//! expression). A name a module only re-exports (`use x::Name` / `pub use x::Name`) is followed
//! to the file that defines it, so a facade (`lib.rs`, a `mod.rs`) is no knot by itself. Test
//! code (`#[cfg(test)]` items and `tests.rs` files) is left out: a test may use the layers
//! above the code it tests. Comments and string literals are skipped.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The files of a crate and who names whom: file (relative to `src`) -> files it depends on.
pub type Graph = BTreeMap<PathBuf, BTreeSet<PathBuf>>;

/// One token of Rust source, as far as module paths need it.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Tok {
    Ident(String),
    PathSep,
    Punct(char),
}

/// Tokens of `src` with comments, strings, char literals and lifetimes dropped.
fn tokens(src: &str) -> Vec<Tok> {
    let b: Vec<char> = src.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        let next = b.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < b.len() && b[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                i += if b[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
        } else if (c == 'r' || c == 'b') && raw_string_start(&b, i).is_some() {
            let (hashes, body) = raw_string_start(&b, i).unwrap();
            i = body;
            loop {
                if i >= b.len() {
                    break;
                }
                if b[i] == '"' && (0..hashes).all(|k| b.get(i + 1 + k) == Some(&'#')) {
                    i += 1 + hashes;
                    break;
                }
                i += 1;
            }
        } else if c == '\'' {
            // A char literal ('x', '\n', '\u{..}') or a lifetime ('a).
            if next == Some('\\') {
                i += 2;
                while i < b.len() && b[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if b.get(i + 2) == Some(&'\'') {
                i += 3;
            } else {
                i += 1;
                while i < b.len() && (b[i].is_alphanumeric() || b[i] == '_') {
                    i += 1;
                }
            }
        } else if c.is_alphabetic() || c == '_' {
            let start = i;
            while i < b.len() && (b[i].is_alphanumeric() || b[i] == '_') {
                i += 1;
            }
            out.push(Tok::Ident(b[start..i].iter().collect()));
        } else if c == ':' && next == Some(':') {
            out.push(Tok::PathSep);
            i += 2;
        } else {
            if !c.is_whitespace() {
                out.push(Tok::Punct(c));
            }
            i += 1;
        }
    }
    out
}

/// `r"`, `r#"`, `br"`…: the number of `#` and where the body starts.
fn raw_string_start(b: &[char], i: usize) -> Option<(usize, usize)> {
    if i > 0 && (b[i - 1].is_alphanumeric() || b[i - 1] == '_') {
        return None;
    }
    let mut j = i;
    if b[j] == 'b' {
        j += 1;
    }
    if b.get(j) != Some(&'r') {
        return None;
    }
    j += 1;
    let mut hashes = 0;
    while b.get(j) == Some(&'#') {
        hashes += 1;
        j += 1;
    }
    (b.get(j) == Some(&'"')).then_some((hashes, j + 1))
}

/// `toks` without the items under `#[cfg(test)]` (an inline `mod tests { … }`, a `mod x;`,
/// a test-only `use` or fn). Returns the kept tokens and the names of test-only `mod x;`.
fn strip_test_items(toks: &[Tok]) -> (Vec<Tok>, BTreeSet<String>) {
    let mut out = Vec::new();
    let mut test_mods = BTreeSet::new();
    let mut i = 0;
    let id = |t: Option<&Tok>, s: &str| matches!(t, Some(Tok::Ident(x)) if x == s);
    let p = |t: Option<&Tok>, c: char| matches!(t, Some(Tok::Punct(x)) if *x == c);
    while i < toks.len() {
        let is_cfg_test = p(toks.get(i), '#')
            && p(toks.get(i + 1), '[')
            && id(toks.get(i + 2), "cfg")
            && p(toks.get(i + 3), '(')
            && id(toks.get(i + 4), "test")
            && p(toks.get(i + 5), ')')
            && p(toks.get(i + 6), ']');
        if !is_cfg_test {
            out.push(toks[i].clone());
            i += 1;
            continue;
        }
        // Skip the item: up to its `;` at depth 0 or its closing brace.
        i += 7;
        if id(toks.get(i), "mod") {
            if let (Some(Tok::Ident(name)), true) = (toks.get(i + 1), p(toks.get(i + 2), ';')) {
                test_mods.insert(name.clone());
            }
        }
        let mut depth = 0i32;
        while i < toks.len() {
            match &toks[i] {
                Tok::Punct('{') | Tok::Punct('(') | Tok::Punct('[') => depth += 1,
                Tok::Punct('}') | Tok::Punct(')') | Tok::Punct(']') => {
                    depth -= 1;
                    if depth == 0 && toks[i] == Tok::Punct('}') {
                        i += 1;
                        break;
                    }
                }
                Tok::Punct(';') if depth == 0 => {
                    i += 1;
                    break;
                }
                _ => {}
            }
            i += 1;
        }
    }
    (out, test_mods)
}

/// A path found in the source: where it starts (`crate`, `super`…, a child module) and its
/// segments, plus whether it is (part of) a `use` item and the name it is bound to there.
struct FoundPath {
    segs: Vec<String>,
    in_use: bool,
    bound: Option<String>,
    /// Part of a `pub use` / `pub(crate) use`: names handed on, no dependency by itself.
    reexport: bool,
}

/// Every module path in `toks`: `use` trees expanded into their leaves, and `a::b::c` paths
/// elsewhere.
fn paths(toks: &[Tok]) -> Vec<FoundPath> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        if toks[i] == Tok::Ident("use".into()) {
            let reexport = is_pub_before(toks, i);
            let first = out.len();
            i += 1;
            use_tree(toks, &mut i, Vec::new(), &mut out);
            for fp in &mut out[first..] {
                // A name the file hands on *and* uses itself is a dependency too.
                let used = fp.bound.as_ref().is_some_and(|b| {
                    toks.iter()
                        .filter(|t| matches!(t, Tok::Ident(x) if x == b))
                        .count()
                        > 1
                });
                fp.reexport = reexport && !used;
            }
            continue;
        }
        if let Tok::Ident(first) = &toks[i] {
            let after_sep = i > 0 && toks[i - 1] == Tok::PathSep;
            if !after_sep && toks.get(i + 1) == Some(&Tok::PathSep) {
                let mut segs = vec![first.clone()];
                let mut j = i + 1;
                while toks.get(j) == Some(&Tok::PathSep) {
                    match toks.get(j + 1) {
                        Some(Tok::Ident(s)) => segs.push(s.clone()),
                        _ => break,
                    }
                    j += 2;
                }
                out.push(FoundPath {
                    segs,
                    in_use: false,
                    bound: None,
                    reexport: false,
                });
                i = j;
                continue;
            }
        }
        i += 1;
    }
    out
}

/// Whether the `use` at `toks[i]` is `pub` / `pub(…)`.
fn is_pub_before(toks: &[Tok], i: usize) -> bool {
    match i.checked_sub(1).map(|k| &toks[k]) {
        Some(Tok::Ident(p)) if p == "pub" => true,
        Some(Tok::Punct(')')) => {
            let open = toks[..i].iter().rposition(|t| *t == Tok::Punct('('));
            matches!(open.and_then(|o| o.checked_sub(1)).map(|k| &toks[k]), Some(Tok::Ident(p)) if p == "pub")
        }
        _ => false,
    }
}

/// Names an item defines in `toks` (at any depth: an over-approximation that only serves to
/// tell a module's own items from names it takes through a glob), and the `#[macro_export]`
/// macros, which live at the crate root whatever file defines them.
fn definitions(toks: &[Tok]) -> (BTreeSet<String>, BTreeSet<String>) {
    const KEYWORDS: [&str; 10] = [
        "fn",
        "struct",
        "enum",
        "union",
        "trait",
        "type",
        "const",
        "static",
        "mod",
        "macro_rules",
    ];
    let (mut defs, mut exported) = (BTreeSet::new(), BTreeSet::new());
    for (k, t) in toks.iter().enumerate() {
        let Tok::Ident(kw) = t else { continue };
        if !KEYWORDS.contains(&kw.as_str()) {
            continue;
        }
        let name_at = if kw == "macro_rules" { k + 2 } else { k + 1 };
        if let Some(Tok::Ident(name)) = toks.get(name_at) {
            defs.insert(name.clone());
            let attr = toks[..k]
                .iter()
                .rev()
                .take(4)
                .any(|t| *t == Tok::Ident("macro_export".into()));
            if kw == "macro_rules" && attr {
                exported.insert(name.clone());
            }
        }
    }
    (defs, exported)
}

/// One `use` tree from `toks[*i]` on, its leaves appended to `out` with `prefix` before them.
fn use_tree(toks: &[Tok], i: &mut usize, prefix: Vec<String>, out: &mut Vec<FoundPath>) {
    let mut segs = prefix;
    if toks.get(*i) == Some(&Tok::PathSep) {
        *i += 1; // `use ::std::…`
    }
    loop {
        match toks.get(*i) {
            Some(Tok::Ident(s)) => {
                segs.push(s.clone());
                *i += 1;
                if toks.get(*i) == Some(&Tok::PathSep) {
                    *i += 1;
                    continue;
                }
                let mut bound = segs.last().cloned();
                if toks.get(*i) == Some(&Tok::Ident("as".into())) {
                    bound = match toks.get(*i + 1) {
                        Some(Tok::Ident(a)) => Some(a.clone()),
                        _ => None,
                    };
                    *i += 2;
                }
                if segs.last().map(String::as_str) == Some("self") {
                    segs.pop();
                    if bound.as_deref() == Some("self") {
                        bound = segs.last().cloned();
                    }
                }
                out.push(FoundPath {
                    segs,
                    in_use: true,
                    bound,
                    reexport: false,
                });
                break;
            }
            Some(Tok::Punct('*')) => {
                *i += 1;
                out.push(FoundPath {
                    segs,
                    in_use: true,
                    bound: None,
                    reexport: false,
                });
                break;
            }
            Some(Tok::Punct('{')) => {
                *i += 1;
                loop {
                    match toks.get(*i) {
                        Some(Tok::Punct('}')) => {
                            *i += 1;
                            break;
                        }
                        Some(Tok::Punct(',')) => *i += 1,
                        None => break,
                        _ => use_tree(toks, i, segs.clone(), out),
                    }
                }
                break;
            }
            _ => break,
        }
    }
}

/// The module path of a file under `src`: `lib.rs` / `main.rs` -> [], `a/mod.rs` -> [a],
/// `a/b.rs` -> [a, b].
fn module_of(rel: &Path) -> Vec<String> {
    let mut m: Vec<String> = rel
        .iter()
        .map(|s| s.to_string_lossy().into_owned())
        .collect();
    let last = m.pop().expect("a file");
    let stem = last.trim_end_matches(".rs");
    let is_root = m.is_empty() && (stem == "lib" || stem == "main");
    if stem != "mod" && !is_root {
        m.push(stem.to_string());
    }
    m
}

fn rs_files(dir: &Path, base: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("dir entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rs_files(&p, base, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p.strip_prefix(base).expect("under src").to_path_buf());
        }
    }
}

/// The file-level dependency graph of the crate whose sources are under `src`.
pub fn file_graph(src: &Path) -> Graph {
    let mut files = Vec::new();
    rs_files(src, src, &mut files);
    struct Parsed {
        module: Vec<String>,
        paths: Vec<FoundPath>,
        test_mods: BTreeSet<String>,
        defs: BTreeSet<String>,
    }
    let mut parsed: BTreeMap<PathBuf, Parsed> = BTreeMap::new();
    // `#[macro_export]` macro -> the module whose file defines it.
    let mut macros: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for rel in &files {
        let text = std::fs::read_to_string(src.join(rel)).expect("read source");
        let (toks, test_mods) = strip_test_items(&tokens(&text));
        let (defs, exported) = definitions(&toks);
        for m in exported {
            macros.insert(m, module_of(rel));
        }
        parsed.insert(
            rel.clone(),
            Parsed {
                module: module_of(rel),
                paths: paths(&toks),
                test_mods,
                defs,
            },
        );
    }
    // Files that are test code: `tests.rs`, or declared by a `#[cfg(test)] mod x;`.
    let mut test_files: BTreeSet<Vec<String>> = BTreeSet::new();
    for p in parsed.values() {
        for m in &p.test_mods {
            let mut t = p.module.clone();
            t.push(m.clone());
            test_files.insert(t);
        }
    }
    let by_module: BTreeMap<Vec<String>, PathBuf> = parsed
        .iter()
        .filter(|(rel, p)| {
            rel.file_name().is_some_and(|n| n != "tests.rs")
                && !test_files.iter().any(|t| p.module.starts_with(t))
        })
        .map(|(rel, p)| (p.module.clone(), rel.clone()))
        .collect();

    // The absolute module path a found path means, as seen from `module`; None when it leaves
    // the crate (std, a dependency, a local variable's field…).
    let absolute = |module: &[String], fp: &FoundPath| -> Option<Vec<String>> {
        let mut segs = fp.segs.iter();
        let first = segs.next()?;
        let mut base: Vec<String> = match first.as_str() {
            "crate" => Vec::new(),
            "self" => module.to_vec(),
            "super" => {
                let mut b = module.to_vec();
                b.pop()?;
                b
            }
            child => {
                let mut b = module.to_vec();
                b.push(child.to_string());
                if !by_module.contains_key(&b) {
                    return None;
                }
                b
            }
        };
        let mut rest: Vec<String> = segs.cloned().collect();
        while rest.first().map(String::as_str) == Some("super") {
            base.pop()?;
            rest.remove(0);
        }
        base.extend(rest);
        Some(base)
    };
    // Names each module binds by `use`: module -> name -> absolute path it stands for.
    let mut imports: BTreeMap<Vec<String>, BTreeMap<String, Vec<String>>> = BTreeMap::new();
    // Modules each module glob-imports (`use a::b::*`).
    let mut globs: BTreeMap<Vec<String>, Vec<Vec<String>>> = BTreeMap::new();
    let defs: BTreeMap<Vec<String>, &BTreeSet<String>> = parsed
        .values()
        .map(|p| (p.module.clone(), &p.defs))
        .collect();
    for p in parsed.values() {
        for fp in p.paths.iter().filter(|fp| fp.in_use) {
            match (&fp.bound, absolute(&p.module, fp)) {
                (Some(name), Some(abs)) => {
                    imports
                        .entry(p.module.clone())
                        .or_default()
                        .insert(name.clone(), abs);
                }
                (None, Some(abs)) => globs.entry(p.module.clone()).or_default().push(abs),
                _ => {}
            }
        }
    }
    // The file an absolute path lands in: its longest prefix that is a file's module, with a
    // name that module merely imports followed to where it comes from.
    let resolve = |abs: &[String]| -> Option<PathBuf> {
        let mut path = abs.to_vec();
        for _ in 0..16 {
            let n = (0..=path.len())
                .rev()
                .find(|&n| by_module.contains_key(&path[..n]))?;
            let module = &path[..n];
            let name = path.get(n);
            let own = name.is_some_and(|x| defs.get(module).is_some_and(|d| d.contains(x)));
            let mut redirect = name
                .filter(|_| !own)
                .and_then(|x| imports.get(module).and_then(|m| m.get(x)))
                .cloned();
            if redirect.is_none() && !own {
                if let Some(x) = name {
                    // A root macro defined elsewhere, or a name a glob brings in.
                    redirect = macros.get(x).filter(|_| module.is_empty()).map(|m| {
                        let mut t = m.clone();
                        t.push(x.clone());
                        t
                    });
                    if redirect.is_none() {
                        redirect = globs.get(module).into_iter().flatten().find_map(|g| {
                            defs.get(g).filter(|d| d.contains(x)).map(|_| {
                                let mut t = g.clone();
                                t.push(x.clone());
                                t
                            })
                        });
                    }
                }
            }
            match redirect.as_ref() {
                Some(target) if !target.starts_with(&path[..n + 1]) && *target != path => {
                    let mut next = target.clone();
                    next.extend(path[n + 1..].iter().cloned());
                    path = next;
                }
                _ => return by_module.get(module).cloned(),
            }
        }
        None
    };

    let mut graph = Graph::new();
    for (rel, p) in &parsed {
        if !by_module.values().any(|f| f == rel) {
            continue;
        }
        let deps = graph.entry(rel.clone()).or_default();
        for fp in p.paths.iter().filter(|fp| !fp.reexport) {
            if let Some(target) = absolute(&p.module, fp).and_then(|a| resolve(&a)) {
                if &target != rel {
                    deps.insert(target);
                }
            }
        }
    }
    graph
}

/// The import circles of `graph`: its strongly connected components of two files or more,
/// each sorted, in a stable order (Tarjan's algorithm).
pub fn circles(graph: &Graph) -> Vec<Vec<PathBuf>> {
    struct State<'a> {
        graph: &'a Graph,
        index: BTreeMap<&'a PathBuf, usize>,
        low: BTreeMap<&'a PathBuf, usize>,
        stack: Vec<&'a PathBuf>,
        on_stack: BTreeSet<&'a PathBuf>,
        out: Vec<Vec<PathBuf>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a PathBuf) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on_stack.insert(v);
        for w in s.graph.get(v).into_iter().flatten() {
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if s.on_stack.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut comp = Vec::new();
            loop {
                let w = s.stack.pop().unwrap();
                s.on_stack.remove(w);
                comp.push(w.clone());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                s.out.push(comp);
            }
        }
    }
    let mut s = State {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out.sort();
    s.out
}

/// A readable account of each circle: its files and the arrows between them.
pub fn describe(graph: &Graph, circles: &[Vec<PathBuf>]) -> String {
    let mut text = String::new();
    for c in circles {
        text += &format!("circle of {} files:\n", c.len());
        for f in c {
            let inside: Vec<String> = graph[f]
                .iter()
                .filter(|t| c.contains(t))
                .map(|t| t.display().to_string())
                .collect();
            text += &format!("  {} -> {}\n", f.display(), inside.join(", "));
        }
    }
    text
}

/// This crate's `src`, or the directory `LAYERING_SRC` names (to run the check on another
/// tree, e.g. an older checkout).
fn host_src() -> PathBuf {
    std::env::var_os("LAYERING_SRC")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("src"))
}

#[test]
fn the_host_has_no_import_circle() {
    let graph = file_graph(&host_src());
    let found = circles(&graph);
    assert!(found.is_empty(), "{}", describe(&graph, &found));
}

/// The graph itself: a deliberate circle through `crate::`, `super::`, a child module, a
/// `use` group and a re-export is found, and a facade or test code makes none.
#[test]
fn the_graph_sees_every_kind_of_path() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path();
    let write = |p: &str, text: &str| {
        let p = src.join(p);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    };
    // lib re-exports everything; a uses b's item through the facade: no circle by itself.
    write(
        "lib.rs",
        "pub mod a; pub mod b; pub mod c; pub mod d; pub mod m;\n\
         pub use b::Item; pub use c::{deep::Deep as D};",
    );
    write("a.rs", "use crate::Item; // crate::c::deep in a comment\n");
    write(
        "b.rs",
        "pub struct Item; #[cfg(test)] mod tests { use crate::a::*; }\n\
         #[cfg(test)] mod more;\n fn f() { let _ = \"crate::a::X\"; }",
    );
    write("b/more.rs", "use crate::a::X;");
    // c/mod.rs defines a trait its child implements and hands the child's type on: a facade
    // re-export is no arrow back. A root macro lives where it is defined.
    write(
        "c/mod.rs",
        "pub mod deep; pub trait T {} pub use deep::Deep;",
    );
    write(
        "c/deep.rs",
        "use super::T; pub struct Deep; impl T for Deep {} pub fn h() {}",
    );
    write("m.rs", "#[macro_export]\nmacro_rules! mac { () => {} }");
    write(
        "d.rs",
        "use crate::mac; use crate::c::*; fn f() { mac!(); }",
    );
    let graph = file_graph(src);
    assert_eq!(circles(&graph), Vec::<Vec<PathBuf>>::new(), "{graph:?}");
    assert!(
        graph[Path::new("a.rs")].contains(Path::new("b.rs")),
        "{graph:?}"
    );
    assert!(graph[Path::new("c/deep.rs")].contains(Path::new("c/mod.rs")));
    assert!(!graph[Path::new("c/mod.rs")].contains(Path::new("c/deep.rs")));
    assert!(
        graph[Path::new("d.rs")].contains(Path::new("m.rs")),
        "{graph:?}"
    );
    assert!(graph[Path::new("d.rs")].contains(Path::new("c/mod.rs")));
    assert!(
        !graph.contains_key(Path::new("b/more.rs")),
        "test-only file"
    );

    // b -> c/deep by an expression path through super's child, c/deep -> a by a use group,
    // a -> b (above): one circle of three.
    write(
        "b.rs",
        "pub struct Item; fn f() { let _ = super::c::deep::h; }",
    );
    write("c/deep.rs", "use crate::{a::{self}}; pub fn h() {}");
    let graph = file_graph(src);
    let found = circles(&graph);
    assert_eq!(
        found,
        vec![vec![
            PathBuf::from("a.rs"),
            PathBuf::from("b.rs"),
            PathBuf::from("c/deep.rs")
        ]],
        "{}",
        describe(&graph, &found)
    );
}

/// The same check over every crate of the workspace and the firmware (`crates/*/src`,
/// `firmware/src`): no crate has an import circle. A crate's own direction between crates is
/// Cargo's to enforce; this holds the direction inside each one.
#[test]
fn no_crate_has_an_import_circle() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root.join("crates"))
        .unwrap()
        .map(|e| e.unwrap().path().join("src"))
        .filter(|p| p.is_dir())
        .collect();
    dirs.push(root.join("firmware/src"));
    dirs.sort();
    assert!(dirs.len() >= 6, "the workspace's crates: {dirs:?}");
    let mut report = String::new();
    for src in &dirs {
        let graph = file_graph(src);
        let found = circles(&graph);
        if !found.is_empty() {
            report += &format!("{}:\n{}", src.display(), describe(&graph, &found));
        }
    }
    assert!(report.is_empty(), "{report}");
}

/// The stack (`crates/stack/src`) names no profile and no product in its code (comments may
/// say which product a switch serves), and no file of it is over 900 lines: a newcomer finds a
/// rule in the file named after its service, not in a long file that mixes them.
#[test]
fn the_stack_names_no_product_and_keeps_its_files_short() {
    // Whole identifiers (short words that occur inside others), and parts of identifiers.
    const WORDS: &[&str] = &[
        "th", "cam", "cams", "models", "sensor", "sensors", "switches",
    ];
    const PARTS: &[&str] = &[
        "tmi",
        "e_series",
        "eseries",
        "encoder",
        "magnet",
        "preset",
        "stroke",
        "window_cam",
        "deviceconfig",
        "canpos_models",
    ];
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../stack/src");
    let mut files = Vec::new();
    rs_files(&src, &src, &mut files);
    assert!(files.len() > 20, "the stack's files: {files:?}");
    let mut found = Vec::new();
    for f in &files {
        let text = std::fs::read_to_string(src.join(f)).unwrap();
        let name = f.file_name().unwrap().to_string_lossy();
        if name == "tests.rs" || name.ends_with("_tests.rs") {
            continue;
        }
        let lines = text.lines().count();
        if lines > 900 {
            found.push(format!("{}: {lines} lines (over 900)", f.display()));
        }
        let (toks, _) = strip_test_items(&tokens(&text));
        for t in toks {
            if let Tok::Ident(x) = t {
                let x_lower = x.to_ascii_lowercase();
                if WORDS.contains(&x_lower.as_str()) || PARTS.iter().any(|p| x_lower.contains(p)) {
                    found.push(format!("{}: names `{x}`", f.display()));
                }
            }
        }
    }
    found.dedup();
    assert!(found.is_empty(), "{}", found.join("\n"));
}
