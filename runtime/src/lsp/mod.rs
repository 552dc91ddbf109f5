//! `softc lsp`: a language server for `.soft` scripts over stdio.
//!
//! Diagnostics come from the same front end and checker as `softc check` (with the script's
//! folder as base directory and the runtime's mesh reader), formatting from `softc fmt`;
//! hover, definition, references, completion and the outline from `softc_compiler::ide`.
//!
//! Robustness: a reader thread frames messages and hands them to the main loop through a
//! channel, so bursts of edits are coalesced (a document is checked once, after the queue is
//! drained). Malformed messages get JSON-RPC errors; each handler runs under `catch_unwind`, so a
//! bug in one request answers that request with an internal error and the server goes on.

pub mod position;
pub mod transport;

use lsp_types as lt;
use position::LineIndex;
use serde_json::{Value, json};
use softc_compiler::diag::Severity;
use softc_compiler::front::{self, ast::Script};
use softc_compiler::ide::{self, Analysis, CompletionKind};
use softc_compiler::sema::CheckOptions;
use softc_compiler::sema::mesh_probe::{MeshProbe, MeshSummary};
use std::collections::HashMap;
use std::io::{BufReader, Write};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, mpsc};
use std::time::SystemTime;
use transport::Incoming;

// JSON-RPC error codes.
const PARSE_ERROR: i64 = -32700;
const INVALID_REQUEST: i64 = -32600;
const METHOD_NOT_FOUND: i64 = -32601;
const INVALID_PARAMS: i64 = -32602;
const INTERNAL_ERROR: i64 = -32603;
const SERVER_NOT_INITIALIZED: i64 = -32002;

type HandlerResult = Result<Value, (i64, String)>;

/// Run the server on standard input and output until `exit` or the end of input. Returns the
/// process exit status: 0 after `shutdown` + `exit` (or end of input after `shutdown`), else 1.
pub fn run_stdio() -> i32 {
    let (tx, rx) = mpsc::channel::<Incoming>();
    std::thread::Builder::new()
        .name("lsp-reader".into())
        .spawn(move || {
            let stdin = std::io::stdin();
            let mut r = BufReader::new(stdin.lock());
            while let Ok(Some(m)) = transport::read_message(&mut r) {
                if tx.send(m).is_err() {
                    break;
                }
            }
        })
        .expect("spawn the reader thread");
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    Server::new().run(rx, &mut out)
}

struct Document {
    text: String,
    version: Option<i32>,
    /// The AST and the checker's results for `text` (`None` until checked, or on a syntax
    /// error), so requests do not parse again.
    parsed: Option<Script>,
    checked: Option<softc_compiler::sema::CheckedScript>,
    /// Diagnostics must be recomputed and published.
    dirty: bool,
}

pub struct Server {
    docs: HashMap<String, Document>,
    initialized: bool,
    shutdown: bool,
    /// Closed documents whose diagnostics must be cleared.
    closed: Vec<String>,
    probe: Arc<CachedProbe>,
}

impl Default for Server {
    fn default() -> Self {
        Self::new()
    }
}

impl Server {
    pub fn new() -> Self {
        Server {
            docs: HashMap::new(),
            initialized: false,
            shutdown: false,
            closed: Vec::new(),
            probe: Arc::new(CachedProbe::default()),
        }
    }

    /// The main loop: handle messages, and publish diagnostics when the queue is empty.
    pub fn run(&mut self, rx: mpsc::Receiver<Incoming>, out: &mut dyn Write) -> i32 {
        loop {
            let msg = match rx.try_recv() {
                Ok(m) => m,
                Err(mpsc::TryRecvError::Empty) => {
                    self.publish_dirty(out);
                    match rx.recv() {
                        Ok(m) => m,
                        Err(_) => return if self.shutdown { 0 } else { 1 },
                    }
                }
                Err(mpsc::TryRecvError::Disconnected) => {
                    return if self.shutdown { 0 } else { 1 };
                }
            };
            if let Some(code) = self.handle(msg, out) {
                return code;
            }
        }
    }

    /// Handle one message; `Some(status)` when the server must exit.
    fn handle(&mut self, msg: Incoming, out: &mut dyn Write) -> Option<i32> {
        let v = match msg {
            Incoming::Message(v) => v,
            Incoming::ParseError(e) => {
                send(
                    out,
                    error_response(Value::Null, PARSE_ERROR, &format!("parse error: {e}")),
                );
                return None;
            }
            Incoming::Invalid(e) => {
                send(out, error_response(Value::Null, INVALID_REQUEST, &e));
                return None;
            }
        };
        let id = v.get("id").cloned();
        let method = v.get("method").and_then(Value::as_str).map(str::to_string);
        let params = v.get("params").cloned().unwrap_or(Value::Null);
        let Some(method) = method else {
            // A response from the client (we send no requests) is ignored; anything else with an
            // id is an invalid request.
            let is_response = v.get("result").is_some() || v.get("error").is_some();
            if !is_response {
                let id = id.filter(valid_id).unwrap_or(Value::Null);
                send(
                    out,
                    error_response(id, INVALID_REQUEST, "not a JSON-RPC request: no method"),
                );
            }
            return None;
        };
        match id {
            Some(id) if !valid_id(&id) => {
                send(
                    out,
                    error_response(
                        Value::Null,
                        INVALID_REQUEST,
                        "the id must be a number or a string",
                    ),
                );
                None
            }
            Some(id) => {
                let result = if !self.initialized && method != "initialize" {
                    Err((
                        SERVER_NOT_INITIALIZED,
                        "the server is not initialized yet".to_string(),
                    ))
                } else if self.shutdown {
                    Err((INVALID_REQUEST, "the server is shutting down".to_string()))
                } else {
                    match catch_unwind(AssertUnwindSafe(|| self.request(&method, params))) {
                        Ok(r) => r,
                        Err(p) => Err((
                            INTERNAL_ERROR,
                            format!("internal error in `{method}`: {}", panic_text(&p)),
                        )),
                    }
                };
                let resp = match result {
                    Ok(r) => json!({"jsonrpc": "2.0", "id": id, "result": r}),
                    Err((code, m)) => error_response(id, code, &m),
                };
                send(out, resp);
                None
            }
            None => {
                if method == "exit" {
                    return Some(if self.shutdown { 0 } else { 1 });
                }
                if catch_unwind(AssertUnwindSafe(|| self.notification(&method, params))).is_err() {
                    eprintln!("softc lsp: internal error while handling `{method}`");
                }
                None
            }
        }
    }

    fn request(&mut self, method: &str, params: Value) -> HandlerResult {
        match method {
            "initialize" if self.initialized => {
                Err((INVALID_REQUEST, "the server is already initialized".into()))
            }
            "initialize" => {
                self.initialized = true;
                Ok(initialize_result())
            }
            "shutdown" => {
                self.shutdown = true;
                Ok(Value::Null)
            }
            "textDocument/hover" => {
                let p: lt::HoverParams = parse(params)?;
                let pos = p.text_document_position_params;
                self.hover(pos.text_document.uri.as_str(), pos.position)
            }
            "textDocument/definition" => {
                let p: lt::GotoDefinitionParams = parse(params)?;
                let pos = p.text_document_position_params;
                self.definition(&pos.text_document.uri, pos.position)
            }
            "textDocument/references" => {
                let p: lt::ReferenceParams = parse(params)?;
                let pos = p.text_document_position;
                self.references(&pos.text_document.uri, pos.position)
            }
            "textDocument/completion" => {
                let p: lt::CompletionParams = parse(params)?;
                let pos = p.text_document_position;
                self.completion(pos.text_document.uri.as_str(), pos.position)
            }
            "textDocument/documentSymbol" => {
                let p: lt::DocumentSymbolParams = parse(params)?;
                self.symbols(p.text_document.uri.as_str())
            }
            "textDocument/formatting" => {
                let p: lt::DocumentFormattingParams = parse(params)?;
                self.formatting(p.text_document.uri.as_str())
            }
            // Lets the tests check that a crashing handler does not stop the server; only when
            // the environment asks for it.
            "softc/panic" if std::env::var_os("SOFTC_LSP_TEST_PANIC").is_some() => {
                panic!("requested panic (softc/panic)")
            }
            _ => Err((METHOD_NOT_FOUND, format!("unknown method `{method}`"))),
        }
    }

    fn notification(&mut self, method: &str, params: Value) {
        if !self.initialized {
            return;
        }
        match method {
            "textDocument/didOpen" => {
                if let Ok(p) = serde_json::from_value::<lt::DidOpenTextDocumentParams>(params) {
                    let d = p.text_document;
                    self.docs.insert(
                        d.uri.as_str().to_string(),
                        Document {
                            text: d.text,
                            version: Some(d.version),
                            parsed: None,
                            checked: None,
                            dirty: true,
                        },
                    );
                }
            }
            "textDocument/didChange" => {
                if let Ok(p) = serde_json::from_value::<lt::DidChangeTextDocumentParams>(params)
                    && let Some(doc) = self.docs.get_mut(p.text_document.uri.as_str())
                {
                    for change in p.content_changes {
                        match change.range {
                            None => doc.text = change.text,
                            Some(range) => {
                                // Incremental changes, in case a client sends them anyway.
                                let idx = LineIndex::new(&doc.text);
                                let a = idx.offset(&doc.text, range.start);
                                let b = idx.offset(&doc.text, range.end).max(a);
                                doc.text.replace_range(a..b, &change.text);
                            }
                        }
                    }
                    doc.version = Some(p.text_document.version);
                    doc.parsed = None;
                    doc.checked = None;
                    doc.dirty = true;
                }
            }
            "textDocument/didClose" => {
                if let Ok(p) = serde_json::from_value::<lt::DidCloseTextDocumentParams>(params)
                    && self.docs.remove(p.text_document.uri.as_str()).is_some()
                {
                    // Clear the closed document's diagnostics in the editor.
                    self.closed.push(p.text_document.uri.as_str().to_string());
                }
            }
            "textDocument/didSave" => {
                // Meshes may have changed on disk: check again.
                if let Ok(p) = serde_json::from_value::<lt::DidSaveTextDocumentParams>(params)
                    && let Some(doc) = self.docs.get_mut(p.text_document.uri.as_str())
                {
                    doc.dirty = true;
                }
            }
            _ => {}
        }
    }

    fn options_for(&self, uri: &str) -> CheckOptions {
        CheckOptions {
            base_dir: file_uri_to_path(uri).and_then(|p| p.parent().map(Path::to_path_buf)),
            mesh_probe: Some(self.probe.clone() as Arc<dyn MeshProbe>),
        }
    }

    /// Check every changed document and publish its diagnostics.
    fn publish_dirty(&mut self, out: &mut dyn Write) {
        for uri in std::mem::take(&mut self.closed) {
            send(
                out,
                json!({
                    "jsonrpc": "2.0",
                    "method": "textDocument/publishDiagnostics",
                    "params": {"uri": uri, "diagnostics": []},
                }),
            );
        }
        let dirty: Vec<String> = self
            .docs
            .iter()
            .filter(|(_, d)| d.dirty)
            .map(|(u, _)| u.clone())
            .collect();
        for uri in dirty {
            let options = self.options_for(&uri);
            let Some(doc) = self.docs.get_mut(&uri) else {
                continue;
            };
            doc.dirty = false;
            let text = doc.text.clone();
            // What `softc_compiler::check_source` does, keeping the AST for later requests.
            let checked = catch_unwind(AssertUnwindSafe(|| match front::parse(&text) {
                Err(d) => (vec![d], None, None),
                Ok(ast) => {
                    let (script, diags) = softc_compiler::sema::check(&ast, &options);
                    (diags, Some(ast), Some(script))
                }
            }));
            let (diags, ast, script) = match checked {
                Ok((d, ast, script)) => (diagnostics_json(&uri, &text, &d), ast, script),
                Err(p) => {
                    let d = json!([{
                        "range": {"start": {"line": 0, "character": 0}, "end": {"line": 0, "character": 0}},
                        "severity": 1,
                        "source": "softc",
                        "message": format!("softc crashed while checking this script (a bug in softc): {}", panic_text(&p)),
                    }]);
                    (d, None, None)
                }
            };
            doc.parsed = ast;
            doc.checked = script;
            let version = doc.version;
            send(
                out,
                json!({
                    "jsonrpc": "2.0",
                    "method": "textDocument/publishDiagnostics",
                    "params": {"uri": uri, "version": version, "diagnostics": diags},
                }),
            );
        }
    }

    fn doc(&self, uri: &str) -> Result<&Document, (i64, String)> {
        self.docs
            .get(uri)
            .ok_or_else(|| (INVALID_PARAMS, format!("the document `{uri}` is not open")))
    }

    fn analysis<'a>(&self, doc: &'a Document) -> Analysis<'a> {
        match &doc.parsed {
            // Checked and parsed: reuse both (they belong to the current text).
            Some(ast) if !doc.dirty => {
                Analysis::from_parsed(&doc.text, Some(ast.clone()), doc.checked.clone())
            }
            _ => Analysis::new(&doc.text),
        }
    }

    fn hover(&self, uri: &str, pos: lt::Position) -> HandlerResult {
        let doc = self.doc(uri)?;
        let idx = LineIndex::new(&doc.text);
        let offset = idx.offset(&doc.text, pos);
        let a = self.analysis(doc);
        Ok(match a.hover(offset) {
            Some((md, span)) => json!({
                "contents": {"kind": "markdown", "value": md},
                "range": idx.range(&doc.text, span.start, span.end),
            }),
            None => Value::Null,
        })
    }

    fn definition(&self, uri: &lt::Uri, pos: lt::Position) -> HandlerResult {
        let doc = self.doc(uri.as_str())?;
        let idx = LineIndex::new(&doc.text);
        let offset = idx.offset(&doc.text, pos);
        let a = self.analysis(doc);
        Ok(match a.definition(offset) {
            Some(span) => {
                json!({"uri": uri.as_str(), "range": idx.range(&doc.text, span.start, span.end)})
            }
            None => Value::Null,
        })
    }

    fn references(&self, uri: &lt::Uri, pos: lt::Position) -> HandlerResult {
        let doc = self.doc(uri.as_str())?;
        let idx = LineIndex::new(&doc.text);
        let offset = idx.offset(&doc.text, pos);
        let a = self.analysis(doc);
        let locs: Vec<Value> = a
            .references(offset)
            .into_iter()
            .map(|s| json!({"uri": uri.as_str(), "range": idx.range(&doc.text, s.start, s.end)}))
            .collect();
        Ok(Value::Array(locs))
    }

    fn completion(&self, uri: &str, pos: lt::Position) -> HandlerResult {
        let doc = self.doc(uri)?;
        let idx = LineIndex::new(&doc.text);
        let offset = idx.offset(&doc.text, pos);
        let a = self.analysis(doc);
        let items: Vec<Value> = a
            .completions(offset)
            .into_iter()
            .map(|c| {
                let kind = match c.kind {
                    CompletionKind::Keyword => lt::CompletionItemKind::KEYWORD,
                    CompletionKind::Variable => lt::CompletionItemKind::VARIABLE,
                    CompletionKind::Function => lt::CompletionItemKind::FUNCTION,
                    CompletionKind::Constant => lt::CompletionItemKind::CONSTANT,
                    CompletionKind::Unit => lt::CompletionItemKind::UNIT,
                    CompletionKind::Setting => lt::CompletionItemKind::PROPERTY,
                    CompletionKind::Argument => lt::CompletionItemKind::FIELD,
                    CompletionKind::Type => lt::CompletionItemKind::TYPE_PARAMETER,
                    CompletionKind::Material => lt::CompletionItemKind::CLASS,
                };
                let mut item = json!({"label": c.label, "kind": kind, "detail": c.detail});
                if let Some(t) = c.insert_text {
                    item["insertText"] = Value::String(t);
                }
                item
            })
            .collect();
        Ok(json!({"isIncomplete": false, "items": items}))
    }

    fn symbols(&self, uri: &str) -> HandlerResult {
        let doc = self.doc(uri)?;
        let idx = LineIndex::new(&doc.text);
        let a = self.analysis(doc);
        fn conv(s: &ide::Symbol, text: &str, idx: &LineIndex) -> Value {
            let kind = match s.kind {
                "mesh" | "region" | "chamber" | "nodes" | "elements" | "obstacle" => {
                    lt::SymbolKind::OBJECT
                }
                "material" => lt::SymbolKind::CLASS,
                "param" => lt::SymbolKind::FIELD,
                "input" => lt::SymbolKind::PROPERTY,
                "let" => lt::SymbolKind::VARIABLE,
                "fn" | "controller" => lt::SymbolKind::FUNCTION,
                _ => lt::SymbolKind::NAMESPACE,
            };
            let range = idx.range(text, s.span.start, s.span.end);
            let sel = idx.range(text, s.name_span.start, s.name_span.end);
            json!({
                "name": s.name,
                "detail": s.kind,
                "kind": kind,
                "range": range,
                "selectionRange": sel,
                "children": s.children.iter().map(|c| conv(c, text, idx)).collect::<Vec<_>>(),
            })
        }
        Ok(Value::Array(
            a.symbols()
                .iter()
                .map(|s| conv(s, &doc.text, &idx))
                .collect(),
        ))
    }

    fn formatting(&self, uri: &str) -> HandlerResult {
        let doc = self.doc(uri)?;
        match softc_compiler::fmt::format_source(&doc.text) {
            // A syntax error: no edit (the diagnostic says why).
            Err(_) => Ok(Value::Null),
            Ok(f) if f == doc.text => Ok(json!([])),
            Ok(f) => {
                let idx = LineIndex::new(&doc.text);
                Ok(json!([{"range": idx.range(&doc.text, 0, doc.text.len()), "newText": f}]))
            }
        }
    }
}

fn initialize_result() -> Value {
    json!({
        "capabilities": {
            "positionEncoding": "utf-16",
            "textDocumentSync": {"openClose": true, "change": 1, "save": {"includeText": false}},
            "hoverProvider": true,
            "definitionProvider": true,
            "referencesProvider": true,
            "completionProvider": {"triggerCharacters": ["(", ","], "resolveProvider": false},
            "documentSymbolProvider": true,
            "documentFormattingProvider": true,
        },
        "serverInfo": {"name": "softc", "version": env!("CARGO_PKG_VERSION")},
    })
}

fn parse<T: serde::de::DeserializeOwned>(params: Value) -> Result<T, (i64, String)> {
    serde_json::from_value(params).map_err(|e| (INVALID_PARAMS, format!("invalid params: {e}")))
}

fn valid_id(id: &Value) -> bool {
    id.is_number() || id.is_string()
}

fn error_response(id: Value, code: i64, message: &str) -> Value {
    json!({"jsonrpc": "2.0", "id": id, "error": {"code": code, "message": message}})
}

fn send(out: &mut dyn Write, msg: Value) {
    struct W<'a>(&'a mut dyn Write);
    impl Write for W<'_> {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.write(b)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            self.0.flush()
        }
    }
    if let Err(e) = transport::write_message(&mut W(out), &msg) {
        eprintln!("softc lsp: cannot write to the client: {e}");
    }
}

fn panic_text(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
}

/// LSP diagnostics for the front end's.
fn diagnostics_json(uri: &str, text: &str, diags: &[softc_compiler::diag::Diagnostic]) -> Value {
    let idx = LineIndex::new(text);
    Value::Array(
        diags
            .iter()
            .map(|d| {
                let mut message = d.message.clone();
                if let Some(h) = &d.hint {
                    message.push_str("\nhint: ");
                    message.push_str(h);
                }
                let related: Vec<Value> = d
                    .notes
                    .iter()
                    .map(|(s, m)| {
                        json!({
                            "location": {"uri": uri, "range": idx.range(text, s.start, s.end)},
                            "message": m,
                        })
                    })
                    .collect();
                let mut v = json!({
                    "range": idx.range(text, d.span.start, d.span.end),
                    "severity": match d.severity { Severity::Error => 1, Severity::Warning => 2 },
                    "code": d.code,
                    "source": "softc",
                    "message": message,
                });
                if !related.is_empty() {
                    v["relatedInformation"] = Value::Array(related);
                }
                v
            })
            .collect(),
    )
}

/// The path of a `file:` URI (percent-decoded); `None` for other schemes.
pub fn file_uri_to_path(uri: &str) -> Option<PathBuf> {
    let rest = uri.strip_prefix("file://")?;
    // Drop the authority (`file://localhost/…`); Windows paths come as `/C:/…`.
    let path = match rest.find('/') {
        Some(i) => &rest[i..],
        None => return None,
    };
    let bytes = path.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%'
            && i + 3 <= bytes.len()
            && let Some(b) = std::str::from_utf8(&bytes[i + 1..i + 3])
                .ok()
                .and_then(|h| u8::from_str_radix(h, 16).ok())
        {
            out.push(b);
            i += 3;
            continue;
        }
        out.push(bytes[i]);
        i += 1;
    }
    let s = String::from_utf8(out).ok()?;
    let s = s.split(['?', '#']).next().unwrap_or("");
    if cfg!(windows) {
        let t = s.trim_start_matches('/');
        return Some(PathBuf::from(t));
    }
    Some(PathBuf::from(s))
}

/// The runtime's mesh reader with a cache, so a keystroke does not re-read an unchanged mesh.
#[derive(Default)]
struct CachedProbe {
    cache: Mutex<HashMap<(PathBuf, u64), CacheEntry>>,
}

struct CacheEntry {
    stamp: Option<(SystemTime, u64)>,
    result: Result<MeshSummary, String>,
}

impl MeshProbe for CachedProbe {
    fn probe(&self, path: &Path, unit: f64) -> Result<MeshSummary, String> {
        let stamp = std::fs::metadata(path)
            .ok()
            .and_then(|m| Some((m.modified().ok()?, m.len())));
        let key = (path.to_path_buf(), unit.to_bits());
        if let Ok(cache) = self.cache.lock()
            && let Some(e) = cache.get(&key)
            && stamp.is_some()
            && e.stamp == stamp
        {
            return e.result.clone();
        }
        let result = crate::mesh::probe::FileProbe.probe(path, unit);
        if let Ok(mut cache) = self.cache.lock() {
            if cache.len() > 16 {
                cache.clear();
            }
            cache.insert(
                key,
                CacheEntry {
                    stamp,
                    result: result.clone(),
                },
            );
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_uris_become_paths() {
        assert_eq!(
            file_uri_to_path("file:///home/a%20b/x.soft"),
            Some(PathBuf::from("/home/a b/x.soft"))
        );
        assert_eq!(
            file_uri_to_path("file://localhost/tmp/x.soft"),
            Some(PathBuf::from("/tmp/x.soft"))
        );
        assert_eq!(file_uri_to_path("untitled:Untitled-1"), None);
        assert_eq!(
            file_uri_to_path("file:///bad%zz"),
            Some(PathBuf::from("/bad%zz"))
        );
        assert_eq!(
            file_uri_to_path("file:///end%4"),
            Some(PathBuf::from("/end%4"))
        );
    }
}
