//! JSON-RPC 2.0 over stdio with LSP's `Content-Length` framing.
//!
//! Hand-written rather than `lsp-server`'s (rust-analyzer's; last weighed at 0.10.0), because a
//! malformed message must be answered with a JSON-RPC error while the server keeps running, and
//! `lsp-server` cannot (runtime/tests/lsp.rs and the test below check most of these cases):
//!
//! - `Connection::stdio`'s reader thread ends the connection on the first message it cannot read.
//! - `Message::read` used directly returns one `InvalidData` error whose text embeds the serde
//!   error, so invalid JSON (-32700) cannot be told from a valid object that is not a request
//!   (-32600) without matching on that text.
//! - `{"id": {"x": 1}, "method": "shutdown"}` deserializes as a *notification* (its `Message` is
//!   an untagged enum and unknown fields are ignored), so a request with a bad id goes unanswered
//!   instead of getting -32600; numeric ids beyond `i32` fall into the same hole.
//! - Its `Response` cannot carry a null id, which JSON-RPC requires for a parse error.
//! - A bad header line (`Content-Length: abc`, a bare `\n`) fails in the middle of the header, so
//!   the rest of that message is read as the next one and a following good message is lost.
//! - The body is allocated at whatever size `Content-Length` says (no limit like `MAX_MESSAGE`).

use serde_json::Value;
use std::io::{self, BufRead, Read, Write};

/// The largest message body read into memory; larger ones are skipped and answered with an error.
pub const MAX_MESSAGE: usize = 64 << 20;

/// One framed message, or why it could not be read.
#[derive(Debug)]
pub enum Incoming {
    Message(Value),
    /// The body was not JSON (answered with a parse error, id null).
    ParseError(String),
    /// The header was malformed or the body too large (answered with invalid request, id null).
    Invalid(String),
}

/// Read the next message. `Ok(None)` at the end of the stream.
pub fn read_message(r: &mut impl BufRead) -> io::Result<Option<Incoming>> {
    let mut length: Option<usize> = None;
    let mut bad_header: Option<String> = None;
    let mut saw_any = false;
    loop {
        let mut line = Vec::new();
        let n = r.by_ref().take(8192).read_until(b'\n', &mut line)?;
        if n == 0 {
            return Ok(None);
        }
        if !line.ends_with(b"\n") {
            // An overlong header line: drop the rest of it.
            let mut rest = Vec::new();
            r.read_until(b'\n', &mut rest)?;
            bad_header = Some("header line too long".into());
            continue;
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches(['\r', '\n']);
        if text.is_empty() {
            if !saw_any {
                // Stray blank line between messages.
                continue;
            }
            break;
        }
        saw_any = true;
        match text.split_once(':') {
            Some((name, value)) if name.trim().eq_ignore_ascii_case("content-length") => {
                match value.trim().parse::<usize>() {
                    Ok(v) => length = Some(v),
                    Err(_) => bad_header = Some(format!("bad Content-Length `{}`", value.trim())),
                }
            }
            Some(_) => {}
            None => bad_header = Some(format!("malformed header line `{text}`")),
        }
    }
    let Some(len) = length else {
        return Ok(Some(Incoming::Invalid(
            bad_header.unwrap_or_else(|| "missing Content-Length header".into()),
        )));
    };
    if len > MAX_MESSAGE {
        // Skip the body without holding it.
        let skipped = io::copy(&mut r.by_ref().take(len as u64), &mut io::sink())?;
        if (skipped as usize) < len {
            return Ok(None);
        }
        return Ok(Some(Incoming::Invalid(format!(
            "message of {len} bytes is larger than the limit of {MAX_MESSAGE} bytes"
        ))));
    }
    let mut body = vec![0u8; len];
    r.read_exact(&mut body)?;
    if let Some(h) = bad_header {
        return Ok(Some(Incoming::Invalid(h)));
    }
    Ok(Some(match serde_json::from_slice::<Value>(&body) {
        Ok(v) => Incoming::Message(v),
        Err(e) => Incoming::ParseError(e.to_string()),
    }))
}

/// Write one message with its header.
pub fn write_message(w: &mut impl Write, msg: &Value) -> io::Result<()> {
    let body = serde_json::to_vec(msg)?;
    write!(w, "Content-Length: {}\r\n\r\n", body.len())?;
    w.write_all(&body)?;
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_all(input: &[u8]) -> Vec<String> {
        let mut r = io::BufReader::new(input);
        let mut out = Vec::new();
        while let Some(m) = read_message(&mut r).unwrap() {
            out.push(match m {
                Incoming::Message(v) => format!("msg {v}"),
                Incoming::ParseError(_) => "parse".into(),
                Incoming::Invalid(_) => "invalid".into(),
            });
        }
        out
    }

    #[test]
    fn frames_good_bad_and_oversized_messages() {
        let mut input = Vec::new();
        input.extend_from_slice(b"Content-Length: 2\r\n\r\n{}");
        input.extend_from_slice(b"Content-Length: 3\r\n\r\n{x}");
        input.extend_from_slice(b"Content-Type: x\r\n\r\n");
        input.extend_from_slice(b"Content-Length: abc\r\n\r\n");
        input.extend_from_slice(b"content-length: 4\r\nContent-Type: utf8\r\n\r\nnull");
        assert_eq!(
            read_all(&input),
            ["msg {}", "parse", "invalid", "invalid", "msg null"]
        );
        let huge = format!("Content-Length: {}\r\n\r\n", MAX_MESSAGE + 1);
        let mut input = huge.into_bytes();
        input.resize(input.len() + MAX_MESSAGE + 1, b' ');
        input.extend_from_slice(b"Content-Length: 1\r\n\r\n1");
        assert_eq!(read_all(&input), ["invalid", "msg 1"]);
    }
}
