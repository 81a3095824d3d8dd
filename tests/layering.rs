//! The module graph, read from the sources in src/: data flows one way (scene -> accel ->
//! integrator -> film -> worker -> service, `cli` on top), the renderer never imports the
//! service, and no two modules import each other (compared as siblings: the children of the
//! parent they share, the top-level modules included). A reference is any `crate::`, `super::` or
//! `self::` path in code outside `#[cfg(test)] mod tests` and comments, braces expanded.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Module path ("service::store::sqlite"; "" for the crate root) -> its file.
fn modules() -> BTreeMap<String, PathBuf> {
    fn walk(dir: &Path, root: &Path, out: &mut BTreeMap<String, PathBuf>) {
        for e in std::fs::read_dir(dir).expect("src folder") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                walk(&p, root, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p.strip_prefix(root).expect("under src").with_extension("");
                let mut parts: Vec<String> = rel
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                if matches!(
                    parts.last().map(String::as_str),
                    Some("mod" | "lib" | "main")
                ) {
                    parts.pop();
                }
                out.insert(parts.join("::"), p);
            }
        }
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut out = BTreeMap::new();
    walk(&root, &root, &mut out);
    out
}

/// The code of a file without its unit tests and comments.
fn code_of(file: &Path) -> String {
    let text = std::fs::read_to_string(file).expect("source file");
    let text = match text.find("#[cfg(test)]\nmod tests") {
        Some(i) => &text[..i],
        None => &text[..],
    };
    text.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// Every path starting with `crate`, `super` or `self` in `code`, as segments; a brace group
/// gives one path per item (its first segment).
fn paths(code: &str) -> Vec<Vec<String>> {
    let b: Vec<char> = code.chars().collect();
    let keywords: Vec<(&str, Vec<char>)> = ["crate::", "super::", "self::"]
        .iter()
        .map(|k| (*k, k.chars().collect()))
        .collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let boundary = i == 0 || !(is_ident(b[i - 1]) || b[i - 1] == ':');
        let starts = keywords
            .iter()
            .find(|(_, chars)| boundary && b[i..].starts_with(chars))
            .map(|(k, _)| *k);
        let Some(kw) = starts else {
            i += 1;
            continue;
        };
        let mut segs = vec![kw.trim_end_matches(':').to_string()];
        i += kw.len();
        loop {
            if b.get(i) == Some(&'{') {
                let mut depth = 0;
                let mut item = String::new();
                let mut items = Vec::new();
                while i < b.len() {
                    let c = b[i];
                    i += 1;
                    match c {
                        '{' => depth += 1,
                        '}' => {
                            depth -= 1;
                            if depth == 0 {
                                items.push(std::mem::take(&mut item));
                                break;
                            }
                        }
                        ',' if depth == 1 => items.push(std::mem::take(&mut item)),
                        _ if depth == 1 => item.push(c),
                        _ => {}
                    }
                }
                for it in items {
                    let first: String = it.trim().chars().take_while(|c| is_ident(*c)).collect();
                    let mut p = segs.clone();
                    if !first.is_empty() && first != "self" {
                        p.push(first);
                    }
                    out.push(p);
                }
                break;
            }
            let ident: String = b[i..].iter().take_while(|c| is_ident(**c)).collect();
            if ident.is_empty() {
                out.push(segs);
                break;
            }
            i += ident.chars().count();
            segs.push(ident);
            if b[i..].starts_with(&[':', ':']) {
                i += 2;
            } else {
                out.push(segs);
                break;
            }
        }
    }
    out
}

/// The module a path in module `from` names (its longest prefix that is a module).
fn resolve(from: &str, path: &[String], mods: &BTreeMap<String, PathBuf>) -> Option<String> {
    let mut base: Vec<String> = if from.is_empty() {
        Vec::new()
    } else {
        from.split("::").map(str::to_string).collect()
    };
    let mut rest = path;
    match rest.first().map(String::as_str) {
        Some("crate") => base.clear(),
        Some("self") => {}
        Some("super") => {
            // A file module's `super` is its parent.
            base.pop();
        }
        _ => return None,
    }
    rest = &rest[1..];
    while rest.first().map(String::as_str) == Some("super") {
        base.pop();
        rest = &rest[1..];
    }
    let full: Vec<String> = base.into_iter().chain(rest.iter().cloned()).collect();
    (1..=full.len())
        .rev()
        .map(|k| full[..k].join("::"))
        .find(|m| mods.contains_key(m))
}

/// Module -> the modules it references (not itself, its ancestors or its descendants).
fn graph() -> BTreeMap<String, BTreeSet<String>> {
    let mods = modules();
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (m, file) in &mods {
        for p in paths(&code_of(file)) {
            let Some(t) = resolve(m, &p, &mods) else {
                continue;
            };
            let related = t == *m
                || m.starts_with(&format!("{t}::"))
                || t.starts_with(&format!("{m}::"))
                || t.is_empty()
                || m.is_empty();
            if !related {
                edges.entry(m.clone()).or_default().insert(t);
            }
        }
    }
    edges
}

/// The children of the deepest module `a` and `b` share that lead to each.
fn siblings(a: &str, b: &str) -> (String, String) {
    let (pa, pb): (Vec<&str>, Vec<&str>) = (a.split("::").collect(), b.split("::").collect());
    let shared = pa.iter().zip(&pb).take_while(|(x, y)| x == y).count();
    (
        pa[..=shared.min(pa.len() - 1)].join("::"),
        pb[..=shared.min(pb.len() - 1)].join("::"),
    )
}

#[test]
fn no_two_modules_import_each_other() {
    let edges = graph();
    assert!(
        edges.values().map(BTreeSet::len).sum::<usize>() > 300,
        "the reader found too few references: {edges:?}"
    );
    let mut between: BTreeMap<(String, String), Vec<(String, String)>> = BTreeMap::new();
    for (a, ts) in &edges {
        for b in ts {
            let (x, y) = siblings(a, b);
            if x != y {
                between
                    .entry((x, y))
                    .or_default()
                    .push((a.clone(), b.clone()));
            }
        }
    }
    let cycles: Vec<String> = between
        .iter()
        .filter(|((x, y), _)| x < y && between.contains_key(&(y.clone(), x.clone())))
        .map(|((x, y), e)| {
            let back = &between[&(y.clone(), x.clone())];
            format!("{x} <-> {y} (e.g. {:?} and {:?})", e[0], back[0])
        })
        .collect();
    assert!(
        cycles.is_empty(),
        "modules that import each other: {cycles:#?}"
    );
}

#[test]
fn data_flows_one_way() {
    let edges = graph();
    let top = |m: &str| m.split("::").next().unwrap_or("").to_string();
    let renderer = [
        "geometry",
        "scene",
        "accel",
        "material",
        "light",
        "camera",
        "sampler",
        "mis",
        "integrator",
        "film",
    ];
    let mut wrong = Vec::new();
    for (a, ts) in &edges {
        for b in ts {
            let (ta, tb) = (top(a), top(b));
            let forbidden = (renderer.contains(&ta.as_str())
                && ["worker", "service", "cli", "protocol", "bundle", "job"]
                    .contains(&tb.as_str()))
                || (ta == "service" && tb == "integrator")
                || (ta == "worker" && ["service", "cli"].contains(&tb.as_str()))
                || (ta != "cli" && tb == "cli");
            if forbidden {
                wrong.push(format!("{a} -> {b}"));
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "imports against the data flow: {wrong:#?}"
    );
}

#[test]
fn the_reader_sees_braced_and_nested_paths() {
    let p = paths("use super::{App, merge::{self, X}};\nlet x = crate::film::Tile::new();");
    assert_eq!(
        p,
        vec![
            vec!["super".to_string(), "App".to_string()],
            vec!["super".to_string(), "merge".to_string()],
            vec![
                "crate".to_string(),
                "film".to_string(),
                "Tile".to_string(),
                "new".to_string()
            ],
        ]
    );
}
