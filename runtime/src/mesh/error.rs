//! Errors of mesh loading, conversion and generation.
//!
//! Every error names the file it concerns and, where it applies, the line (or byte offset of
//! binary data), the element/face/node, and says how to fix the input.

use std::fmt;
use std::path::{Path, PathBuf};

use super::validate::MeshIssue;

/// What went wrong, for callers that branch on it (tests, the CLI's exit codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshErrorKind {
    /// The file could not be opened, read or written.
    Io,
    /// The file is malformed (syntax, counts, numbers, indices).
    Parse,
    /// The file is well formed but uses something softc does not support.
    Unsupported,
    /// The mesh parsed but failed validation (see [`MeshError::issues`]).
    Invalid,
    /// A mesh generation spec is wrong.
    Spec,
}

/// A mesh error with enough context for a person to fix the input. Boxed to keep `Result`s
/// small; the fields are reached through `Deref` (`err.kind`, `err.line`, ...).
#[derive(Debug, Clone)]
pub struct MeshError(Box<MeshErrorData>);

/// The contents of a [`MeshError`].
#[derive(Debug, Clone)]
pub struct MeshErrorData {
    pub kind: MeshErrorKind,
    /// The file concerned, when there is one.
    pub file: Option<PathBuf>,
    /// 1-based line number in a text file.
    pub line: Option<usize>,
    /// Byte offset in a binary file.
    pub offset: Option<usize>,
    /// What is wrong.
    pub message: String,
    /// How to fix it.
    pub fix: Option<String>,
    /// Validation issues (for [`MeshErrorKind::Invalid`]).
    pub issues: Vec<MeshIssue>,
}

impl MeshError {
    pub fn new(kind: MeshErrorKind, message: impl Into<String>) -> Self {
        MeshError(Box::new(MeshErrorData {
            kind,
            file: None,
            line: None,
            offset: None,
            message: message.into(),
            fix: None,
            issues: Vec::new(),
        }))
    }
    pub fn parse(message: impl Into<String>) -> Self {
        Self::new(MeshErrorKind::Parse, message)
    }
    pub fn unsupported(message: impl Into<String>) -> Self {
        Self::new(MeshErrorKind::Unsupported, message)
    }
    pub fn spec(message: impl Into<String>) -> Self {
        Self::new(MeshErrorKind::Spec, message)
    }
    pub fn io(path: &Path, err: &std::io::Error) -> Self {
        Self::new(MeshErrorKind::Io, format!("{err}")).in_file(path)
    }
    pub fn in_file(mut self, path: &Path) -> Self {
        if self.file.is_none() {
            self.file = Some(path.to_path_buf());
        }
        self
    }
    pub fn at_line(mut self, line: usize) -> Self {
        self.line = Some(line);
        self
    }
    pub fn at_offset(mut self, offset: usize) -> Self {
        self.offset = Some(offset);
        self
    }
    pub fn with_fix(mut self, fix: impl Into<String>) -> Self {
        self.fix = Some(fix.into());
        self
    }
}

impl std::ops::Deref for MeshError {
    type Target = MeshErrorData;
    fn deref(&self) -> &MeshErrorData {
        &self.0
    }
}

impl std::ops::DerefMut for MeshError {
    fn deref_mut(&mut self) -> &mut MeshErrorData {
        &mut self.0
    }
}

impl fmt::Display for MeshError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.file {
            Some(p) => write!(f, "{}", p.display())?,
            None => write!(f, "<mesh>")?,
        }
        if let Some(l) = self.line {
            write!(f, ":{l}")?;
        }
        if let Some(o) = self.offset {
            write!(f, " (byte {o})")?;
        }
        write!(f, ": {}", self.message)?;
        for issue in self.issues.iter().take(20) {
            write!(f, "\n  {issue}")?;
        }
        if self.issues.len() > 20 {
            write!(f, "\n  ... and {} more issues", self.issues.len() - 20)?;
        }
        if let Some(fix) = &self.fix {
            write!(f, "\n  fix: {fix}")?;
        }
        Ok(())
    }
}

impl std::error::Error for MeshError {}
