//! The guide (`docs/`, mdBook), the README and the language reference are checked like code:
//! every `.soft` snippet by `softc check`, every command marked `<!-- run -->` by running it,
//! every relative link and anchor by resolving it, the generated reference pages against the
//! program, and the book by building it. docs/src/contributing.md states the conventions.

use softc_tests::{bless, files_under, root, scratch, softc};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A fenced code block: its language, text, the 1-based line of its opening fence, and the HTML
/// comment on the line before the fence (`<!-- ... -->`), if any.
struct Block {
    lang: String,
    text: String,
    line: usize,
    note: Option<String>,
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The guide's pages, sorted.
fn guide_pages() -> Vec<PathBuf> {
    let pages = files_under(&root().join("docs/src"), "md");
    assert!(pages.len() > 10, "the guide has pages: {pages:?}");
    pages
}

/// A page's text with mdBook's `{{#include PATH}}` directives replaced by the files (paths
/// relative to the page), as the book shows it.
fn expanded(page: &Path) -> String {
    let text = read(page);
    let mut out = String::new();
    let mut rest = text.as_str();
    while let Some(start) = rest.find("{{#include ") {
        out.push_str(&rest[..start]);
        let end = rest[start..]
            .find("}}")
            .unwrap_or_else(|| panic!("{}: an include is not closed", page.display()));
        let target = rest[start + "{{#include ".len()..start + end].trim();
        let path = page.parent().unwrap().join(target);
        assert!(
            path.is_file(),
            "{}: `{{{{#include {target}}}}}` names no file",
            page.display()
        );
        out.push_str(read(&path).trim_end_matches('\n'));
        rest = &rest[start + end + 2..];
    }
    out.push_str(rest);
    out
}

/// The fenced code blocks of a Markdown text.
fn blocks(text: &str) -> Vec<Block> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i].trim_start();
        if let Some(info) = line.strip_prefix("```") {
            let lang = info.split([',', ' ']).next().unwrap_or("").to_string();
            let note = lines[..i]
                .iter()
                .rev()
                .find(|l| !l.trim().is_empty())
                .map(|l| l.trim())
                .filter(|l| l.starts_with("<!--") && l.ends_with("-->"))
                .map(|l| l[4..l.len() - 3].trim().to_string());
            let start = i;
            i += 1;
            let mut body = Vec::new();
            while i < lines.len() && !lines[i].trim_start().starts_with("```") {
                body.push(lines[i]);
                i += 1;
            }
            out.push(Block {
                lang,
                text: body.join("\n") + "\n",
                line: start + 1,
                note,
            });
        }
        i += 1;
    }
    out
}

/// The text outside code blocks (links in code are not links).
fn prose(text: &str) -> String {
    let mut out = String::new();
    let mut in_code = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_code = !in_code;
            continue;
        }
        if !in_code {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// A scratch folder where scripts and commands see the repository's `examples/` and `meshes/`
/// (read only by convention), and where `meshes/...` also resolves from inside `examples/`.
fn workspace(tag: &str) -> PathBuf {
    let dir = scratch("docs", tag);
    link_repository_folders(&dir, &["examples", "meshes"]);
    link_repository_folders(&dir.join("snippets"), &["examples", "meshes"]);
    dir
}

/// `dir/NAME` → the repository's `NAME`, for each name (made once; `dir` created).
fn link_repository_folders(dir: &Path, names: &[&str]) {
    std::fs::create_dir_all(dir).unwrap();
    for name in names {
        let link = dir.join(name);
        if !link.exists() {
            std::os::unix::fs::symlink(root().join(name), &link).unwrap();
        }
    }
}

// The language reference checks fragments in a small scene (its section 1's), as its
// annotations say: `top` adds declarations, `mat` a material, `sim` lines of the sim block, `opt`
// params and an optimize block.
const SCENE_HEAD: &str = "mesh body = load(\"meshes/cuboid.msh\")\n\
    chamber cavity = surface(body, \"cavity\")\n\
    region clamp = box(min: [-1, -1, -1] mm, max: [0.5, 11, 11] mm)\n\
    nodes tip = select(body, x > 59.9 mm)\n";
const SCENE_MATERIAL: &str =
    "material silicone = neo_hookean(mu: 10 kPa, kappa: 1 MPa, density: 1070 kg/m^3)\n";
const SCENE_SIM: &str = "sim {\n  dt = 20 us\n  duration = 0.1 s\n  fix clamp\n  \
    pressure cavity = 2 kPa * ramp(t, 0.05 s)\n}\n";
const SCENE_LOSS: &str = "loss = mean(n in tip) (x[n].z - x0[n].z + 1 mm)^2 at end\n";

/// The script a snippet is checked as, for the mode of its annotation.
fn script_for(mode: &str, snippet: &str) -> Option<String> {
    Some(match mode {
        "full" => snippet.to_string(),
        "top" => format!("{SCENE_HEAD}{SCENE_MATERIAL}{snippet}\n{SCENE_SIM}"),
        "mat" => format!("{SCENE_HEAD}{snippet}\n{SCENE_SIM}"),
        "sim" => format!(
            "{SCENE_HEAD}{SCENE_MATERIAL}sim {{\n  dt = 20 us\n  duration = 0.1 s\n  \
             fix clamp\n  pressure cavity = 2 kPa\n{snippet}}}\n{SCENE_LOSS}"
        ),
        "opt" => format!("{SCENE_HEAD}{SCENE_MATERIAL}{SCENE_SIM}{SCENE_LOSS}{snippet}"),
        _ => return None,
    })
}

/// The codes `softc check` reports for a script.
fn codes_of(path: &Path) -> (Vec<String>, String) {
    let (_, out, err) = softc(&["check", "--message-format", "json", path.to_str().unwrap()]);
    let mut codes = Vec::new();
    for line in out.lines().filter(|l| l.starts_with('{')) {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        if let Some(code) = v["code"].as_str() {
            codes.push(code.to_string());
        }
    }
    (codes, out + &err)
}

/// Every `.soft` block checks as its annotation says: `check: MODE ok [WARNINGS]` (no errors,
/// only the warnings listed) or `check: MODE CODES` (those errors and no other error; warnings
/// allowed). Without an annotation a block is `full ok`.
#[test]
fn every_soft_snippet_checks_as_annotated() {
    let dir = workspace("snippets").join("snippets");
    let mut sources: Vec<(PathBuf, String)> = guide_pages()
        .into_iter()
        .map(|p| {
            let text = expanded(&p);
            (p, text)
        })
        .collect();
    for extra in ["README.md", "lang-spec/SPEC.md"] {
        sources.push((root().join(extra), read(&root().join(extra))));
    }
    let mut failures = Vec::new();
    let mut checked = 0;
    for (page, text) in &sources {
        for block in blocks(text).into_iter().filter(|b| b.lang == "soft") {
            let place = format!("{}:{}", page.display(), block.line);
            let note = block.note.as_deref().unwrap_or("check: full ok");
            let Some(spec) = note.strip_prefix("check:") else {
                failures.push(format!("{place}: the note before a soft block is `{note}`"));
                continue;
            };
            let mut words = spec.split_whitespace();
            let mode = words.next().unwrap_or("");
            let expected: Vec<&str> = words.collect();
            if mode == "prelude" {
                // The reference quotes the prelude verbatim: it must be the compiled one.
                if block.text != softc_compiler::sema::PRELUDE {
                    failures.push(format!(
                        "{place}: the quoted prelude differs from compiler/src/sema/prelude.soft"
                    ));
                }
                continue;
            }
            // `in DIR`: the script's folder is DIR of the repository (its relative paths
            // resolve from there).
            let folder = match (expected.iter().position(|w| *w == "in"), expected.last()) {
                (Some(_), Some(rel)) => {
                    link_repository_folders(&dir.join("nested"), &["meshes"]);
                    let d = dir.join("nested").join(rel);
                    std::fs::create_dir_all(&d).unwrap();
                    d
                }
                _ => dir.clone(),
            };
            let expected: Vec<&str> = expected
                .iter()
                .copied()
                .take_while(|w| *w != "in")
                .collect();
            let Some(script) = script_for(mode, &block.text) else {
                failures.push(format!("{place}: unknown check mode `{mode}`"));
                continue;
            };
            checked += 1;
            let file = folder.join(format!("snippet_{checked}.soft"));
            std::fs::write(&file, &script).unwrap();
            let (codes, report) = codes_of(&file);
            // Where errors are expected, the scene around a fragment may also warn.
            let errors_expected = expected.iter().any(|c| c.starts_with('E'));
            let unexpected: Vec<&String> = codes
                .iter()
                .filter(|c| !expected.contains(&c.as_str()))
                .filter(|c| !(errors_expected && c.starts_with('W')))
                .collect();
            let missing: Vec<&&str> = expected
                .iter()
                .filter(|c| c.starts_with('E') && !codes.iter().any(|d| d == *c))
                .collect();
            if !unexpected.is_empty() || !missing.is_empty() {
                failures.push(format!(
                    "{place} ({note}): reported {codes:?}, expected {expected:?}\n{script}\n{report}"
                ));
            }
        }
    }
    assert!(checked > 40, "only {checked} soft blocks found");
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

/// Split a command line into words: whitespace separates, single and double quotes group, `#`
/// starts a comment.
fn words(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut word = String::new();
    let mut quote = None;
    let mut any = false;
    for c in line.chars() {
        match (quote, c) {
            (None, '"' | '\'') => {
                quote = Some(c);
                any = true;
            }
            (Some(q), c) if c == q => quote = None,
            // A comment: `#` at the start of a word, outside quotes.
            (None, '#') if !any => break,
            (None, c) if c.is_whitespace() => {
                if any {
                    out.push(std::mem::take(&mut word));
                    any = false;
                }
            }
            (_, c) => {
                word.push(c);
                any = true;
            }
        }
    }
    if any {
        out.push(word);
    }
    out
}

/// Shell blocks in the guide and the README: those marked `<!-- run -->` run here (each line
/// that starts with `softc`, in a scratch folder with the repository's `examples/` and
/// `meshes/`) and must succeed; every other one says it is not run and why.
#[test]
fn every_command_shown_is_run_or_marked_as_not_run() {
    let mut pages = guide_pages();
    pages.push(root().join("README.md"));
    let mut to_run = Vec::new();
    let mut failures = Vec::new();
    for page in &pages {
        for block in blocks(&expanded(page)) {
            if !["sh", "bash", "shell"].contains(&block.lang.as_str()) {
                continue;
            }
            let place = format!("{}:{}", page.display(), block.line);
            if block.note.as_deref() == Some("run") {
                let joined = block.text.replace("\\\n", " ");
                for line in joined.lines().map(str::trim) {
                    if line.is_empty() || line.starts_with('#') {
                        continue;
                    }
                    if !line.starts_with("softc ") {
                        failures.push(format!("{place}: `{line}` is not a softc command"));
                        continue;
                    }
                    to_run.push((page.clone(), place.clone(), line.to_string()));
                }
            } else if !block.text.contains("not run by the tests") {
                failures.push(format!(
                    "{place}: a command block neither marked `<!-- run -->` nor saying \
                     `# not run by the tests: why`"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(to_run.len() >= 10, "{to_run:?}");
    // Commands name paths relative to the repository, as a reader types them: run each page's
    // from a scratch folder of its own (this is the only test of this binary that changes the
    // working directory).
    for (page, place, line) in &to_run {
        let tag = page
            .strip_prefix(root())
            .unwrap()
            .to_str()
            .unwrap()
            .replace('/', "-");
        std::env::set_current_dir(workspace(&tag)).unwrap();
        let args = words(line);
        let args: Vec<&str> = args[1..].iter().map(String::as_str).collect();
        let (code, out, err) = softc(&args);
        assert_eq!(code, 0, "{place}: `{line}` exited {code}\n{out}\n{err}");
    }
}

/// A path with its `..` and `.` components resolved (the file need not exist).
fn normalized(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

/// GitHub's and mdBook's anchor of a heading: lower case, letters, digits, `-` and `_` kept,
/// spaces to `-`, everything else dropped.
fn slug(heading: &str) -> String {
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

fn anchors(text: &str) -> Vec<String> {
    prose(text)
        .lines()
        .filter(|l| l.starts_with('#'))
        .map(|l| slug(l.trim_start_matches('#')))
        .collect()
}

/// Relative links (and their anchors) in the guide, the README and every Markdown file they
/// include resolve in the repository.
#[test]
fn relative_links_and_anchors_resolve() {
    let mut files: Vec<PathBuf> = guide_pages();
    for extra in [
        "README.md",
        "ARCHITECTURE.md",
        "lang-spec/SPEC.md",
        "meshes/README.md",
        "lang-spec/editors/README.md",
    ] {
        files.push(root().join(extra));
    }
    let mut failures = Vec::new();
    let mut links = 0;
    for file in &files {
        let text = prose(&read(file));
        let mut rest = text.as_str();
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            let Some(end) = rest.find(')') else { break };
            let target = &rest[..end];
            if target.contains("://") || target.starts_with("mailto:") || target.contains(' ') {
                continue;
            }
            links += 1;
            let (path, anchor) = target.split_once('#').unwrap_or((target, ""));
            let resolved = if path.is_empty() {
                file.clone()
            } else {
                file.parent().unwrap().join(path)
            };
            if !resolved.exists() {
                failures.push(format!("{}: `{target}` names nothing", file.display()));
                continue;
            }
            // The book holds only what is under docs/src: a page that links outside it has a
            // broken link in the HTML (include the file as a page instead).
            let book = root().join("docs/src");
            if file.starts_with(&book) && !normalized(&resolved).starts_with(&book) {
                failures.push(format!(
                    "{}: `{target}` leaves docs/src: the built book will not have it",
                    file.display()
                ));
            }
            if !anchor.is_empty() && resolved.extension().is_some_and(|e| e == "md") {
                // A guide page that includes another file has that file's headings.
                let shown = if resolved.starts_with(root().join("docs/src")) {
                    expanded(&resolved)
                } else {
                    read(&resolved)
                };
                if !anchors(&shown).iter().any(|a| a == anchor) {
                    failures.push(format!(
                        "{}: `{target}`: no heading `#{anchor}` in {}",
                        file.display(),
                        resolved.display()
                    ));
                }
            }
        }
    }
    assert!(links > 50, "only {links} links found");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Every page is in the book's table of contents, and every entry there is a page.
#[test]
fn the_table_of_contents_lists_every_page() {
    let src = root().join("docs/src");
    let summary = read(&src.join("SUMMARY.md"));
    for page in guide_pages() {
        let rel = page
            .strip_prefix(&src)
            .unwrap()
            .to_str()
            .unwrap()
            .to_string();
        if rel != "SUMMARY.md" {
            assert!(
                summary.contains(&format!("]({rel})")),
                "docs/src/{rel} is not in SUMMARY.md"
            );
        }
    }
}

/// Compare a generated page with its file, or rewrite it under `SOFTC_BLESS=1`.
fn golden_page(rel: &str, generated: &str) {
    let path = root().join(rel);
    if bless() {
        std::fs::write(&path, generated).unwrap();
        return;
    }
    let current = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        current == generated,
        "{rel} is out of date: regenerate it with `SOFTC_BLESS=1 cargo test -p softc-tests \
         --test docs` and review the diff"
    );
}

/// The names of a help text's subcommands (its `Commands:` section, `help` left out).
fn subcommands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter(|l| l.len() > 2 && !l.starts_with("   "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|name| *name != "help")
        .map(str::to_string)
        .collect()
}

/// docs/src/reference/cli-help.md is every command's `--help`, as the program prints it.
#[test]
fn the_command_reference_is_the_programs_help() {
    let mut page = String::from(
        "# Every command's help\n\n<!-- Generated by tests/docs.rs from the program's --help: \
         `SOFTC_BLESS=1 cargo test -p softc-tests --test docs` after a change. -->\n\n\
         What `softc COMMAND --help` prints, for every command. The [overview](cli.md) has one \
         line per command.\n",
    );
    let mut queue = vec![vec![]];
    while let Some(path) = queue.pop() {
        let mut args: Vec<&str> = path.iter().map(String::as_str).collect();
        args.push("--help");
        let (code, help, err) = softc(&args);
        assert_eq!(code, 0, "{args:?}: {err}");
        let name = std::iter::once("softc")
            .chain(path.iter().map(String::as_str))
            .collect::<Vec<_>>()
            .join(" ");
        page.push_str(&format!(
            "\n## `{name}`\n\n```text\n{}\n```\n",
            help.trim_end()
        ));
        for sub in subcommands(&help).into_iter().rev() {
            let mut next = path.clone();
            next.push(sub);
            queue.push(next);
        }
    }
    assert!(page.matches("\n## ").count() >= 10, "{page}");
    golden_page("docs/src/reference/cli-help.md", &page);
}

/// docs/src/reference/errors.md: every code with its meaning (the language reference's section
/// 12) and the diagnostics corpus' scripts that produce it, with their messages. Every code the
/// compiler emits has a row there.
#[test]
fn the_error_code_reference_covers_every_code() {
    let spec = read(&root().join("lang-spec/SPEC.md"));
    let section = spec
        .split("## 12. Error and warning codes")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("SPEC section 12");
    let mut meanings = BTreeMap::new();
    for row in section
        .lines()
        .filter(|l| l.starts_with("| E") || l.starts_with("| W"))
    {
        let cells: Vec<&str> = row.trim_matches('|').split(" | ").map(str::trim).collect();
        meanings.insert(
            cells[0].to_string(),
            (cells[1].to_string(), cells[2].to_string()),
        );
    }
    // Every code in the compiler's and runtime's sources: a string literal `"E0201"`.
    let mut emitted = std::collections::BTreeSet::new();
    for dir in ["compiler/src", "runtime/src"] {
        for path in files_under(&root().join(dir), "rs") {
            let text = read(&path);
            for (i, _) in text.match_indices('"') {
                let code = text.get(i + 1..i + 6).unwrap_or("");
                if text.get(i + 6..i + 7) == Some("\"")
                    && (code.starts_with('E') || code.starts_with('W'))
                    && code[1..].chars().all(|c| c.is_ascii_digit())
                {
                    emitted.insert(code.to_string());
                }
            }
        }
    }
    let undocumented: Vec<&String> = emitted
        .iter()
        .filter(|c| !meanings.contains_key(*c))
        .collect();
    assert!(
        undocumented.is_empty(),
        "codes emitted but not in SPEC section 12: {undocumented:?}"
    );
    // The corpus: each script's first comment line says what is wrong; its snapshot lists the
    // diagnostics.
    let corpus = root().join("tests/diagnostics");
    let mut examples: BTreeMap<String, Vec<(String, String, String)>> = BTreeMap::new();
    for script in softc_tests::files_with_ext(&corpus, "soft") {
        let name = script.file_name().unwrap().to_str().unwrap().to_string();
        let what = String::from_utf8_lossy(&std::fs::read(&script).unwrap())
            .lines()
            .next()
            .unwrap_or("")
            .trim_start_matches('#')
            .trim()
            .to_string();
        let snap = read(&script.with_extension("snap"));
        let lines: Vec<&str> = snap.lines().skip(3).collect();
        for line in &lines {
            if let Some(code) = line.split('[').nth(1).and_then(|s| s.get(..5)) {
                let entry = examples.entry(code.to_string()).or_default();
                if !entry.iter().any(|(n, _, _)| *n == name) {
                    entry.push((name.clone(), what.clone(), line.to_string()));
                }
            }
        }
    }
    let mut page = String::from(
        "# Error and warning codes\n\n<!-- Generated by tests/docs.rs from lang-spec/SPEC.md \
         section 12 and the diagnostics corpus (tests/diagnostics): `SOFTC_BLESS=1 cargo test \
         -p softc-tests --test docs` after a change. -->\n\n\
         Every code `softc check` (and `softc run`, for what only the mesh or the run can tell) \
         reports, with its meaning, an example, and up to three scripts of the diagnostics \
         corpus (`tests/diagnostics/`, each a small script with one mistake) with the messages \
         they get. Codes are stable: a tool may match on them. `E` codes are errors (exit \
         status 1), `W` codes warnings (`--deny-warnings` makes them errors).\n",
    );
    for (code, (meaning, example)) in &meanings {
        let mut first = meaning.chars();
        let meaning: String = first
            .next()
            .map(|c| c.to_uppercase().chain(first).collect())
            .unwrap_or_default();
        page.push_str(&format!(
            "\n## {code}\n\n{meaning}.\n\nExample: {example}.\n"
        ));
        match examples.get(code) {
            Some(cases) => {
                page.push_str("\nFrom the corpus:\n\n");
                for (name, what, line) in cases.iter().take(3) {
                    page.push_str(&format!(
                        "- `{name}`: {what}\n\n  ```text\n  {line}\n  ```\n"
                    ));
                }
            }
            None => page.push_str("\nNo script of the corpus triggers it.\n"),
        }
    }
    golden_page("docs/src/reference/errors.md", &page);
}

/// `mdbook build` succeeds without warnings. It runs where mdBook is installed (`.ci/run`
/// installs it); under `CI=true` it must.
#[test]
fn the_book_builds() {
    let probe = std::process::Command::new("mdbook")
        .arg("--version")
        .output();
    if probe.is_err() {
        assert!(
            std::env::var("CI").ok().as_deref() != Some("true"),
            "CI=true: mdbook must be installed (.ci/run installs it with cargo install)"
        );
        eprintln!("note: mdbook is not installed; the book was not built");
        return;
    }
    let out_dir = scratch("docs", "book");
    let run = std::process::Command::new("mdbook")
        .arg("build")
        .arg(root().join("docs"))
        .arg("--dest-dir")
        .arg(&out_dir)
        .output()
        .unwrap();
    let log =
        String::from_utf8_lossy(&run.stdout).to_string() + &String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "mdbook build failed:\n{log}");
    assert!(
        !log.contains("WARN") && !log.contains("ERROR"),
        "mdbook build warned:\n{log}"
    );
    assert!(
        out_dir.join("index.html").exists()
            && out_dir.join("tutorials/first-actuator.html").exists()
    );
    std::fs::remove_dir_all(&out_dir).ok();
}
