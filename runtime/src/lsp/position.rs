//! Byte offsets (the compiler's spans) ↔ LSP positions (line, UTF-16 code unit).

use lsp_types::Position;
use serde_json::{Value, json};

/// Start offsets of the lines of a text.
pub struct LineIndex {
    starts: Vec<usize>,
}

impl LineIndex {
    pub fn new(text: &str) -> Self {
        let mut starts = vec![0];
        starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        LineIndex { starts }
    }

    /// The position of a byte offset (clamped to the text and to a character boundary).
    pub fn position(&self, text: &str, offset: usize) -> Position {
        let mut o = offset.min(text.len());
        while !text.is_char_boundary(o) {
            o -= 1;
        }
        let line = match self.starts.binary_search(&o) {
            Ok(i) => i,
            Err(i) => i - 1,
        };
        let col: usize = text[self.starts[line]..o]
            .chars()
            .map(char::len_utf16)
            .sum();
        Position::new(line as u32, col as u32)
    }

    /// The byte offset of a position; past the end of a line is the line's end, past the last
    /// line the end of the text, inside a surrogate pair the character's start.
    pub fn offset(&self, text: &str, pos: Position) -> usize {
        let Some(&start) = self.starts.get(pos.line as usize) else {
            return text.len();
        };
        let end = self
            .starts
            .get(pos.line as usize + 1)
            .map_or(text.len(), |e| e - 1);
        let line = &text[start..end];
        let line = line.strip_suffix('\r').unwrap_or(line);
        let mut units = 0usize;
        for (i, c) in line.char_indices() {
            if units >= pos.character as usize {
                return start + i;
            }
            units += c.len_utf16();
            if units > pos.character as usize {
                return start + i;
            }
        }
        start + line.len()
    }

    /// An LSP range as JSON.
    pub fn range(&self, text: &str, start: usize, end: usize) -> Value {
        let s = self.position(text, start);
        let e = self.position(text, end.max(start));
        json!({
            "start": {"line": s.line, "character": s.character},
            "end": {"line": e.line, "character": e.character},
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utf16_columns() {
        // `µ` is 2 bytes / 1 UTF-16 unit; `𝑥` is 4 bytes / 2 units.
        let text = "let a = 1 µm # 𝑥 y\nb\r\nc";
        let idx = LineIndex::new(text);
        let y = text.find(" y").unwrap() + 1;
        assert_eq!(idx.position(text, y), Position::new(0, 18));
        assert_eq!(idx.offset(text, Position::new(0, 18)), y);
        let m = text.find('m').unwrap();
        assert_eq!(idx.position(text, m), Position::new(0, 11));
        assert_eq!(idx.offset(text, Position::new(0, 11)), m);
        // Past the end of a CRLF line: before the `\r`.
        assert_eq!(
            idx.offset(text, Position::new(1, 99)),
            text.find("\r").unwrap()
        );
        assert_eq!(idx.offset(text, Position::new(9, 0)), text.len());
        assert_eq!(idx.position(text, 10_000), Position::new(2, 1));
        // Inside a surrogate pair: the character's start.
        let x = text.find('𝑥').unwrap();
        assert_eq!(idx.offset(text, Position::new(0, 16)), x);
    }
}
