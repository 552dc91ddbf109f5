//! Diagnostics: what went wrong, where, and how to fix it.
//!
//! Human format: a gcc-style first line, so editors and terminals link the location, then the
//! snippet drawn by `codespan-reporting` (secondary locations labelled in the same snippet):
//!
//! ```text
//! examples/bad.soft:7:9: error[E0201]: cannot add pressure (kPa) and length (mm)
//!   |
//! 6 | let a = 3 kPa
//!   |     - declared here
//! 7 | let b = a + 2 mm
//!   |         ^^^^^^^^
//!   |
//!   = hint: both sides of `+` and `-` need the same dimension
//! ```
//!
//! Machine format: one JSON object per line (`--message-format json`).

use crate::front::ast::Span;
use codespan_reporting::diagnostic as cs;
use codespan_reporting::files::{Files, SimpleFile};
use codespan_reporting::term;
use serde::Serialize;
use std::sync::OnceLock;

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    Warning,
    Error,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Diagnostic {
    pub severity: Severity,
    /// Stable code, e.g. `E0201`; documented in lang-spec/SPEC.md.
    pub code: &'static str,
    pub message: String,
    pub span: Span,
    /// Secondary locations (e.g. the first declaration of a duplicate).
    pub notes: Vec<(Span, String)>,
    pub hint: Option<String>,
}

impl Diagnostic {
    pub fn error(code: &'static str, span: Span, message: impl Into<String>) -> Self {
        Diagnostic {
            severity: Severity::Error,
            code,
            message: message.into(),
            span,
            notes: Vec::new(),
            hint: None,
        }
    }
    pub fn warning(code: &'static str, span: Span, message: impl Into<String>) -> Self {
        Diagnostic {
            severity: Severity::Warning,
            ..Diagnostic::error(code, span, message)
        }
    }
    pub fn with_hint(mut self, hint: impl Into<String>) -> Self {
        self.hint = Some(hint.into());
        self
    }
    pub fn with_note(mut self, span: Span, note: impl Into<String>) -> Self {
        self.notes.push((span, note.into()));
        self
    }
    pub fn is_error(&self) -> bool {
        self.severity == Severity::Error
    }
}

/// A source file for rendering: its display name and text.
pub struct SourceFile<'a> {
    pub name: &'a str,
    pub text: &'a str,
    line_starts: Vec<usize>,
    /// The text as snippets show it, built on the first `render`.
    shown: OnceLock<SimpleFile<&'a str, String>>,
}

/// The most characters of a source line a snippet shows (minified or binary input).
const MAX_SHOWN: usize = 200;

impl<'a> SourceFile<'a> {
    pub fn new(name: &'a str, text: &'a str) -> Self {
        let mut line_starts = vec![0];
        line_starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        SourceFile {
            name,
            text,
            line_starts,
            shown: OnceLock::new(),
        }
    }

    /// 1-based line and column (column counted in characters) of a byte offset.
    pub fn line_col(&self, offset: usize) -> (usize, usize) {
        let offset = self.clamp(offset);
        let line = match self.line_starts.binary_search(&offset) {
            Ok(i) => i,
            Err(i) => i - 1,
        };
        let col = self.text[self.line_starts[line]..offset].chars().count() + 1;
        (line + 1, col)
    }

    fn clamp(&self, offset: usize) -> usize {
        let mut o = offset.min(self.text.len());
        while !self.text.is_char_boundary(o) {
            o -= 1;
        }
        o
    }

    /// The text handed to `codespan-reporting`: the same lines, each without its `\r`, cut at
    /// `MAX_SHOWN` characters, control characters (but tabs) shown as `�`.
    fn shown(&self) -> &SimpleFile<&'a str, String> {
        self.shown.get_or_init(|| {
            let mut shown = String::with_capacity(self.text.len().min(1 << 20));
            for (i, line) in self.text.split('\n').enumerate() {
                if i > 0 {
                    shown.push('\n');
                }
                let line = line.strip_suffix('\r').unwrap_or(line);
                shown.extend(line.chars().take(MAX_SHOWN).map(printable));
            }
            SimpleFile::new(self.name, shown)
        })
    }

    /// Where a byte offset of the text falls in the shown text (same line, same character
    /// column, clamped to what is shown).
    fn shown_offset(&self, offset: usize) -> usize {
        let offset = self.clamp(offset);
        let line = match self.line_starts.binary_search(&offset) {
            Ok(i) => i,
            Err(i) => i - 1,
        };
        let column = self.text[self.line_starts[line]..offset].chars().count();
        let shown = self.shown();
        let Ok(range) = shown.line_range((), line) else {
            return shown.source().len();
        };
        let text = &shown.source()[range.clone()];
        let text = text.strip_suffix('\n').unwrap_or(text);
        range.start
            + text
                .char_indices()
                .nth(column)
                .map_or(text.len(), |(i, _)| i)
    }

    /// Render one diagnostic in the human format.
    pub fn render(&self, d: &Diagnostic) -> String {
        let mut out = self.render_short(d);
        out.push('\n');
        let shown = self.shown();
        let range = |span: Span| {
            let start = self.shown_offset(span.start);
            let mut end = self.shown_offset(span.end.max(span.start));
            if end == start {
                // An empty span still gets a caret: under the character it points at.
                end += shown.source()[start..]
                    .chars()
                    .next()
                    .filter(|&c| c != '\n')
                    .map_or(0, char::len_utf8);
            }
            start..end
        };
        let mut labels = vec![cs::Label::primary((), range(d.span))];
        for (span, note) in &d.notes {
            labels.push(cs::Label::secondary((), range(*span)).with_message(note));
        }
        // The header is ours (above); codespan draws the snippet, notes and hint.
        let severity = match d.severity {
            Severity::Error => cs::Severity::Error,
            Severity::Warning => cs::Severity::Warning,
        };
        let snippet = cs::Diagnostic::new(severity)
            .with_labels(labels)
            .with_notes(d.hint.iter().map(|h| format!("hint: {h}")).collect());
        let config = term::Config {
            chars: term::Chars::ascii(),
            ..term::Config::default()
        };
        if let Ok(text) = term::emit_into_string(&config, shown, &snippet) {
            // Drop codespan's header (`error: `) and locus (`--> FILE:LINE:COL`) lines, both
            // already in ours, and its closing empty line; no trailing blanks (codespan pads the
            // gutter of multi-line spans).
            let mut lines: Vec<&str> = text.lines().skip(2).map(str::trim_end).collect();
            if lines.last() == Some(&"") {
                lines.pop();
            }
            for line in lines {
                out.push_str(line);
                out.push('\n');
            }
        } else if let Some(h) = &d.hint {
            // Unreachable (the ranges are valid offsets of the shown text); the hint still counts.
            out.push_str(&format!("  = hint: {h}\n"));
        }
        out
    }

    /// Render one diagnostic as a single-line JSON object.
    pub fn render_json(&self, d: &Diagnostic) -> String {
        #[derive(Serialize)]
        struct Pos {
            line: usize,
            column: usize,
            offset: usize,
        }
        #[derive(Serialize)]
        struct Note {
            message: String,
            start: Pos,
            end: Pos,
        }
        #[derive(Serialize)]
        struct Json<'a> {
            file: &'a str,
            severity: Severity,
            code: &'a str,
            message: &'a str,
            start: Pos,
            end: Pos,
            hint: Option<&'a str>,
            notes: Vec<Note>,
        }
        let pos = |o: usize| {
            let (line, column) = self.line_col(o);
            Pos {
                line,
                column,
                offset: self.clamp(o),
            }
        };
        let json = Json {
            file: self.name,
            severity: d.severity,
            code: d.code,
            message: &d.message,
            start: pos(d.span.start),
            end: pos(d.span.end),
            hint: d.hint.as_deref(),
            notes: d
                .notes
                .iter()
                .map(|(s, m)| Note {
                    message: m.clone(),
                    start: pos(s.start),
                    end: pos(s.end),
                })
                .collect(),
        };
        serde_json::to_string(&json).unwrap_or_default()
    }

    /// `FILE:LINE:COL: severity[CODE]: message` only — the golden-file form.
    pub fn render_short(&self, d: &Diagnostic) -> String {
        let (line, col) = self.line_col(d.span.start);
        let sev = match d.severity {
            Severity::Error => "error",
            Severity::Warning => "warning",
        };
        format!(
            "{}:{}:{}: {}[{}]: {}",
            self.name, line, col, sev, d.code, d.message
        )
    }
}

fn printable(c: char) -> char {
    if c.is_control() && c != '\t' {
        '\u{fffd}'
    } else {
        c
    }
}

/// Find the closest candidate to `name` (for "did you mean" hints).
pub fn did_you_mean<'a>(
    name: &str,
    candidates: impl IntoIterator<Item = &'a str>,
) -> Option<&'a str> {
    let mut best: Option<(usize, &str)> = None;
    for c in candidates {
        let d = edit_distance(&name.to_lowercase(), &c.to_lowercase());
        let limit = (name.chars().count().max(c.chars().count()) / 3).max(1);
        if d <= limit && best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, c));
        }
    }
    best.map(|(_, c)| c)
}

/// Optimal-string-alignment distance: insertions, deletions, substitutions and swaps of two
/// neighbouring characters (`clmap` → `clamp` is one edit).
fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    if a.len() > 64 || b.len() > 64 {
        return usize::MAX / 2;
    }
    let (n, m) = (a.len(), b.len());
    let mut d = vec![vec![0usize; m + 1]; n + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, cell) in d[0].iter_mut().enumerate() {
        *cell = j;
    }
    for i in 1..=n {
        for j in 1..=m {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut v = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                v = v.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = v;
        }
    }
    d[n][m]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn render(text: &str, d: Diagnostic) -> String {
        SourceFile::new("x.soft", text).render(&d)
    }

    #[test]
    fn human_format() {
        let text = "let a = 3 kPa\nlet b = a + 2 mm\n";
        let d = Diagnostic::error("E0201", Span { start: 22, end: 30 }, "cannot add")
            .with_note(Span { start: 4, end: 5 }, "declared here")
            .with_hint("same dimension");
        assert_eq!(
            render(text, d),
            "x.soft:2:9: error[E0201]: cannot add\n  |\n1 | let a = 3 kPa\n  |     - declared here\n\
             2 | let b = a + 2 mm\n  |         ^^^^^^^^\n  |\n  = hint: same dimension\n"
        );
        // A span over two lines; CRLF line ends.
        let d = Diagnostic::warning("W0001", Span { start: 8, end: 18 }, "w");
        assert_eq!(
            render("let a = (1 +\r\n  2)\r\n", d),
            "x.soft:1:9: warning[W0001]: w\n  |\n1 |   let a = (1 +\n  | /---------^\n\
             2 | |   2)\n  | \\----^\n"
        );
    }

    #[test]
    fn snippets_survive_odd_input() {
        // Control characters as `\u{fffd}`, with a caret under them.
        let d = Diagnostic::error("E0003", Span { start: 2, end: 3 }, "control");
        assert_eq!(
            render("a \u{1b}[31m b", d),
            "x.soft:1:3: error[E0003]: control\n  |\n1 | a \u{fffd}[31m b\n  |   ^\n"
        );
        // An empty span at the end of the file still gets a caret.
        let d = Diagnostic::error("E0003", Span { start: 5, end: 5 }, "eof");
        assert_eq!(
            render("let (", d),
            "x.soft:1:6: error[E0003]: eof\n  |\n1 | let (\n  |      ^\n"
        );
        // Long lines are cut, and the carets with them; spans past the end are clamped.
        let long = format!("{}é{}", "x".repeat(300), "y".repeat(300));
        let d = Diagnostic::error(
            "E0001",
            Span {
                start: 190,
                end: 400,
            },
            "long",
        );
        let out = render(&long, d);
        assert!(
            out.starts_with("x.soft:1:191: error[E0001]: long\n"),
            "{out}"
        );
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines[2], format!("1 | {}", "x".repeat(200)));
        assert_eq!(
            lines[3],
            format!("  | {}{}", " ".repeat(190), "^".repeat(10))
        );
        for (start, end) in [(10_000, 20_000), (301, 301), (301, 302), (5, 2)] {
            let d = Diagnostic::error("E0001", Span { start, end }, "odd");
            assert!(render(&long, d).contains('^'), "{start}..{end}");
        }
    }
}
