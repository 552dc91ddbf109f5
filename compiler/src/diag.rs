//! Diagnostics: what went wrong, where, and how to fix it.
//!
//! Human format (gcc-style, so editors and terminals link the location):
//!
//! ```text
//! examples/bad.soft:3:18: error[E0201]: cannot add pressure (kPa) and length (mm)
//!    |
//!  3 | let x = 3 kPa + 2 mm
//!    |         ^^^^^^^^^^^^
//!    = hint: …
//! ```
//!
//! Machine format: one JSON object per line (`--message-format json`).

use crate::front::ast::Span;
use serde::Serialize;
use std::fmt::Write as _;

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
}

impl<'a> SourceFile<'a> {
    pub fn new(name: &'a str, text: &'a str) -> Self {
        let mut line_starts = vec![0];
        line_starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        SourceFile {
            name,
            text,
            line_starts,
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

    fn line_text(&self, line: usize) -> &str {
        let start = self.line_starts[line - 1];
        let end = self
            .line_starts
            .get(line)
            .map(|e| e - 1)
            .unwrap_or(self.text.len());
        self.text[start..end].trim_end_matches('\r')
    }

    /// Render one diagnostic in the human format.
    pub fn render(&self, d: &Diagnostic) -> String {
        let mut out = String::new();
        let (line, col) = self.line_col(d.span.start);
        let sev = match d.severity {
            Severity::Error => "error",
            Severity::Warning => "warning",
        };
        let _ = writeln!(
            out,
            "{}:{}:{}: {}[{}]: {}",
            self.name, line, col, sev, d.code, d.message
        );
        self.render_snippet(&mut out, d.span, None);
        for (span, note) in &d.notes {
            let (nl, nc) = self.line_col(span.start);
            let _ = writeln!(out, "{}:{}:{}: note: {}", self.name, nl, nc, note);
            self.render_snippet(&mut out, *span, None);
        }
        if let Some(h) = &d.hint {
            let _ = writeln!(out, "  = hint: {h}");
        }
        out
    }

    fn render_snippet(&self, out: &mut String, span: Span, label: Option<&str>) {
        let (line, col) = self.line_col(span.start);
        let (end_line, end_col) = self.line_col(span.end.max(span.start));
        let text = self.line_text(line);
        // Keep snippets readable for minified or binary input.
        let shown: String = text.chars().take(200).map(printable).collect();
        let width = line.to_string().len();
        let caret_len = if end_line == line {
            end_col.saturating_sub(col).max(1)
        } else {
            text.chars().count().saturating_sub(col - 1).max(1)
        };
        let pad: String = text
            .chars()
            .take(col - 1)
            .map(|c| if c == '\t' { '\t' } else { ' ' })
            .collect();
        let _ = writeln!(out, "{:width$} |", "");
        let _ = writeln!(out, "{line:>width$} | {shown}");
        let carets = "^".repeat(caret_len.min(200));
        match label {
            Some(l) => {
                let _ = writeln!(out, "{:width$} | {pad}{carets} {l}", "");
            }
            None => {
                let _ = writeln!(out, "{:width$} | {pad}{carets}", "");
            }
        }
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
