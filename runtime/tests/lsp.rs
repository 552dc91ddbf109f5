//! `softc lsp` end to end: spawn the binary, speak JSON-RPC over its stdio, check the answers.
//! Every wait has a timeout, so a hung server fails the test instead of blocking CI.

use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const TIMEOUT: Duration = Duration::from_secs(60);

struct Client {
    child: Child,
    /// `None` once closed ([`Client::close_input`]).
    stdin: Option<ChildStdin>,
    rx: mpsc::Receiver<Value>,
    next_id: i64,
    /// Notifications received while waiting for responses.
    notifications: Vec<Value>,
}

fn read_frame(r: &mut impl BufRead) -> Option<Value> {
    let mut len = None;
    loop {
        let mut line = String::new();
        if r.read_line(&mut line).ok()? == 0 {
            return None;
        }
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some(v) = line.strip_prefix("Content-Length:") {
            len = v.trim().parse::<usize>().ok();
        }
    }
    let mut body = vec![0; len?];
    r.read_exact(&mut body).ok()?;
    Some(serde_json::from_slice(&body).expect("the server sends valid JSON"))
}

impl Client {
    fn start() -> Client {
        let mut child = Command::new(env!("CARGO_BIN_EXE_softc"))
            .arg("lsp")
            .env("SOFTC_LSP_TEST_PANIC", "1")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn softc lsp");
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(stdout);
            while let Some(v) = read_frame(&mut r) {
                if tx.send(v).is_err() {
                    break;
                }
            }
        });
        Client {
            child,
            stdin: Some(stdin),
            rx,
            next_id: 1,
            notifications: Vec::new(),
        }
    }

    fn send_raw(&mut self, body: &[u8]) {
        let stdin = self.stdin.as_mut().expect("the input is open");
        write!(stdin, "Content-Length: {}\r\n\r\n", body.len()).unwrap();
        stdin.write_all(body).unwrap();
        stdin.flush().unwrap();
    }

    /// Close the server's input (the editor went away).
    fn close_input(&mut self) {
        self.stdin = None;
    }

    fn send(&mut self, v: &Value) {
        self.send_raw(&serde_json::to_vec(v).unwrap());
    }

    fn notify(&mut self, method: &str, params: Value) {
        self.send(&json!({"jsonrpc": "2.0", "method": method, "params": params}));
    }

    /// The next message from the server that is a response (notifications are kept).
    fn next_response(&mut self) -> Value {
        let deadline = Instant::now() + TIMEOUT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let v = self
                .rx
                .recv_timeout(left)
                .expect("the server answered in time");
            if v.get("method").is_some() {
                self.notifications.push(v);
            } else {
                return v;
            }
        }
    }

    /// Send a request and return the whole response object (result or error).
    fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        self.send(&json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params}));
        let r = self.next_response();
        assert_eq!(r["id"], json!(id), "response to the request: {r}");
        r
    }

    fn result(&mut self, method: &str, params: Value) -> Value {
        let r = self.call(method, params);
        assert!(r.get("error").is_none(), "{method} failed: {r}");
        r["result"].clone()
    }

    /// Wait for the diagnostics of `uri`.
    fn diagnostics(&mut self, uri: &str) -> Vec<Value> {
        let deadline = Instant::now() + TIMEOUT;
        loop {
            if let Some(i) = self.notifications.iter().position(|n| {
                n["method"] == "textDocument/publishDiagnostics" && n["params"]["uri"] == uri
            }) {
                let n = self.notifications.remove(i);
                return n["params"]["diagnostics"].as_array().unwrap().clone();
            }
            let left = deadline.saturating_duration_since(Instant::now());
            let v = self
                .rx
                .recv_timeout(left)
                .expect("diagnostics were published in time");
            self.notifications.push(v);
        }
    }

    fn initialize(&mut self) -> Value {
        let r = self.result(
            "initialize",
            json!({"processId": null, "rootUri": null, "capabilities": {}}),
        );
        self.notify("initialized", json!({}));
        r
    }

    fn open(&mut self, uri: &str, text: &str) {
        self.notify(
            "textDocument/didOpen",
            json!({"textDocument": {"uri": uri, "languageId": "soft", "version": 1, "text": text}}),
        );
    }

    /// shutdown + exit; the process must end with status 0.
    fn finish(mut self) {
        let r = self.result("shutdown", Value::Null);
        assert_eq!(r, Value::Null);
        self.notify("exit", Value::Null);
        let deadline = Instant::now() + TIMEOUT;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                assert!(status.success(), "softc lsp exited with {status}");
                return;
            }
            assert!(Instant::now() < deadline, "softc lsp did not exit");
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn file_uri(p: &Path) -> String {
    format!("file://{}", p.display()).replace(' ', "%20")
}

fn pos(line: u32, character: u32) -> Value {
    json!({"line": line, "character": character})
}

/// Line and UTF-16 column of the first occurrence of `needle` (plus `delta` characters).
fn find(text: &str, needle: &str, delta: usize) -> Value {
    let at = text.find(needle).unwrap_or_else(|| panic!("{needle}"));
    let line = text[..at].matches('\n').count();
    let line_start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let col: usize = text[line_start..at].chars().map(char::len_utf16).sum();
    pos(line as u32, (col + delta) as u32)
}

const SCRIPT: &str = r#"mesh body = load("../meshes/cuboid.msh")
material silicone = neo_hookean(mu: 10 kPa, kappa: 1 MPa, density: 1070 kg/m^3)
chamber cavity = surface(body, "cavity")
region clamp = box(min: [-1, -1, -1] mm, max: [0.5, 11, 11] mm)
param p_max: pressure = 1 kPa in [0 kPa, 50 kPa]
let bad = 2 kPa + 3 µm
sim {
  dt = 10 us
  steps = 100
  use silicone
  fix clamp
  pressure cavity = p_max * ramp(t, 0.5 s)
}
"#;

#[test]
fn a_session_answers_every_feature() {
    let mut c = Client::start();
    let init = c.initialize();
    let caps = &init["capabilities"];
    assert_eq!(caps["textDocumentSync"]["change"], 1, "{init}");
    for cap in [
        "hoverProvider",
        "definitionProvider",
        "documentSymbolProvider",
        "documentFormattingProvider",
    ] {
        assert_eq!(caps[cap], true, "{cap}: {init}");
    }
    assert!(caps["completionProvider"].is_object(), "{init}");
    assert_eq!(init["serverInfo"]["name"], "softc");

    // The document lives in examples/ (not on disk), so the mesh path resolves against the
    // repository's meshes/ and the mesh probe reads the real cuboid.
    let uri = file_uri(&repo().join("examples").join("lsp-test-unsaved.soft"));
    c.open(&uri, SCRIPT);
    let diags = c.diagnostics(&uri);
    let e = diags
        .iter()
        .find(|d| d["code"] == "E0201")
        .unwrap_or_else(|| panic!("E0201 expected: {diags:?}"));
    // `2 kPa + 3 µm`: characters 10..22 of line 5 (the `µ` is one UTF-16 unit, two bytes).
    assert_eq!(e["range"], json!({"start": pos(5, 10), "end": pos(5, 22)}));
    assert_eq!(e["severity"], 1);
    assert_eq!(e["source"], "softc");
    let msg = e["message"].as_str().unwrap();
    assert!(
        msg.contains("cannot add pressure") && msg.contains("hint:"),
        "{msg}"
    );
    let w = diags.iter().find(|d| d["code"] == "W0001").expect("W0001");
    assert_eq!(w["severity"], 2);
    assert_eq!(diags.len(), 2, "only the planted problems: {diags:?}");

    // Hover on the use of the param: its declaration with type and unit.
    let use_at = find(SCRIPT, "p_max *", 2);
    let h = c.result(
        "textDocument/hover",
        json!({"textDocument": {"uri": uri}, "position": use_at}),
    );
    let hv = h["contents"]["value"].as_str().unwrap();
    assert!(
        hv.contains("param p_max: pressure [Pa] = 1 kPa in [0 kPa, 50 kPa]"),
        "{hv}"
    );
    assert_eq!(h["range"]["start"], find(SCRIPT, "p_max *", 0));
    // Hover on a unit and on a built-in function.
    let h = c.result(
        "textDocument/hover",
        json!({"textDocument": {"uri": uri}, "position": find(SCRIPT, "MPa", 1)}),
    );
    assert!(
        h["contents"]["value"]
            .as_str()
            .unwrap()
            .contains("1 MPa = 1000000 Pa"),
        "{h}"
    );
    let h = c.result(
        "textDocument/hover",
        json!({"textDocument": {"uri": uri}, "position": find(SCRIPT, "ramp", 1)}),
    );
    assert!(
        h["contents"]["value"]
            .as_str()
            .unwrap()
            .contains("ramp(t: time, duration: time)"),
        "{h}"
    );
    let h = c.result(
        "textDocument/hover",
        json!({"textDocument": {"uri": uri}, "position": find(SCRIPT, "neo_hookean", 1)}),
    );
    assert!(
        h["contents"]["value"]
            .as_str()
            .unwrap()
            .contains("material neo_hookean(mu: pressure, kappa: pressure, density: density)"),
        "{h}"
    );

    // Definition of the chamber named in the pressure statement.
    let def = c.result(
        "textDocument/definition",
        json!({"textDocument": {"uri": uri}, "position": find(SCRIPT, "cavity =", 3)}),
    );
    assert_eq!(def["uri"], uri.as_str());
    assert_eq!(
        def["range"],
        json!({"start": pos(2, 8), "end": pos(2, 14)}),
        "{def}"
    );

    // Document symbols: every declaration and the sim block.
    let syms = c.result(
        "textDocument/documentSymbol",
        json!({"textDocument": {"uri": uri}}),
    );
    let names: Vec<&str> = syms
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        ["body", "silicone", "cavity", "clamp", "p_max", "bad", "sim"]
    );
    assert_eq!(
        syms[4]["selectionRange"],
        json!({"start": pos(4, 6), "end": pos(4, 11)})
    );

    // Completion after a partial keyword, on a new line.
    let edited = format!("{SCRIPT}mat");
    c.notify(
        "textDocument/didChange",
        json!({"textDocument": {"uri": uri, "version": 2}, "contentChanges": [{"text": edited}]}),
    );
    let r = c.result(
        "textDocument/completion",
        json!({"textDocument": {"uri": uri}, "position": pos(13, 3)}),
    );
    let labels: Vec<&str> = r["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["label"].as_str().unwrap())
        .collect();
    assert!(labels.contains(&"material"), "{labels:?}");
    assert!(
        !labels.contains(&"sim"),
        "filtered by the prefix: {labels:?}"
    );
    // The syntax error of the edit is published, with the new version.
    let diags = c.diagnostics(&uri);
    assert!(
        diags
            .iter()
            .any(|d| d["code"] == "E0002" || d["severity"] == 1),
        "{diags:?}"
    );
    // Formatting a document with a syntax error: no edit.
    let f = c.result(
        "textDocument/formatting",
        json!({"textDocument": {"uri": uri}, "options": {"tabSize": 2, "insertSpaces": true}}),
    );
    assert_eq!(f, Value::Null);

    // Units after a number, settings in sim.
    let r = c.result(
        "textDocument/completion",
        json!({"textDocument": {"uri": uri}, "position": find(SCRIPT, "0.5 s", 4)}),
    );
    let labels: Vec<String> = r["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["label"].as_str().unwrap().to_string())
        .collect();
    assert!(labels.contains(&"ms".to_string()), "{labels:?}");

    // Formatting: the canonical text (`softc fmt`'s).
    let messy = "param  p : pressure=1 kPa\nlet q=p*2\n";
    let furi = "untitled:messy.soft";
    c.open(furi, messy);
    let f = c.result(
        "textDocument/formatting",
        json!({"textDocument": {"uri": furi}, "options": {"tabSize": 2, "insertSpaces": true}}),
    );
    let edits = f.as_array().unwrap();
    assert_eq!(edits.len(), 1, "{f}");
    let expected = softc_compiler::fmt::format_source(messy).unwrap();
    assert_eq!(edits[0]["newText"], expected.as_str());
    assert_eq!(expected, "param p: pressure = 1 kPa\nlet q = p * 2\n");
    assert_eq!(
        edits[0]["range"],
        json!({"start": pos(0, 0), "end": pos(2, 0)})
    );

    c.finish();
}

#[test]
fn malformed_requests_get_errors_and_the_server_keeps_answering() {
    let mut c = Client::start();
    // Before initialize: "server not initialized".
    let r = c.call("textDocument/hover", json!({}));
    assert_eq!(r["error"]["code"], -32002, "{r}");
    c.initialize();

    // Closing a document clears its diagnostics.
    c.open("untitled:closed.soft", "let a = 1 kPa + 1 mm\n");
    assert!(!c.diagnostics("untitled:closed.soft").is_empty());
    c.notify(
        "textDocument/didClose",
        json!({"textDocument": {"uri": "untitled:closed.soft"}}),
    );
    assert!(c.diagnostics("untitled:closed.soft").is_empty());

    // A ranged (incremental) change is applied too: `1 kPa` becomes `1 mm + 1 kPa`.
    c.open("untitled:inc.soft", "# µ\nlet a = 1 µm; let b = 1 kPa\n");
    let before = c.diagnostics("untitled:inc.soft");
    assert!(before.iter().all(|d| d["code"] != "E0201"), "{before:?}");
    c.notify(
        "textDocument/didChange",
        json!({"textDocument": {"uri": "untitled:inc.soft", "version": 2}, "contentChanges": [
            {"range": {"start": pos(1, 24), "end": pos(1, 24)}, "text": "mm + 1 "}
        ]}),
    );
    let after = c.diagnostics("untitled:inc.soft");
    let e = after.iter().find(|d| d["code"] == "E0201").expect("E0201");
    // `1 mm + 1 kPa` at characters 22..34 (the `µ` before it is one UTF-16 unit).
    assert_eq!(
        e["range"],
        json!({"start": pos(1, 22), "end": pos(1, 34)}),
        "{after:?}"
    );

    // Invalid JSON: a parse error with id null.
    c.send_raw(b"{\"jsonrpc\": \"2.0\", \"id\": 99, \"method\": ");
    let r = c.next_response();
    assert_eq!(r["error"]["code"], -32700, "{r}");
    assert_eq!(r["id"], Value::Null);
    // Not a request object.
    c.send_raw(b"[1, 2, 3]");
    let r = c.next_response();
    assert_eq!(r["error"]["code"], -32600, "{r}");
    // A bad id.
    c.send(&json!({"jsonrpc": "2.0", "id": {"x": 1}, "method": "shutdown"}));
    let r = c.next_response();
    assert_eq!(r["error"]["code"], -32600, "{r}");
    // A header without Content-Length.
    let stdin = c.stdin.as_mut().unwrap();
    stdin.write_all(b"Content-Type: nothing\r\n\r\n").unwrap();
    stdin.flush().unwrap();
    let r = c.next_response();
    assert_eq!(r["error"]["code"], -32600, "{r}");

    // Unknown method.
    let r = c.call("textDocument/doesNotExist", json!({}));
    assert_eq!(r["error"]["code"], -32601, "{r}");
    // Bad params: wrong shapes, missing fields, a document that is not open.
    let r = c.call("textDocument/hover", json!({"textDocument": 3}));
    assert_eq!(r["error"]["code"], -32602, "{r}");
    let r = c.call("textDocument/completion", json!(null));
    assert_eq!(r["error"]["code"], -32602, "{r}");
    let r = c.call(
        "textDocument/definition",
        json!({"textDocument": {"uri": "file:///not/open.soft"}, "position": pos(0, 0)}),
    );
    assert_eq!(r["error"]["code"], -32602, "{r}");
    // A handler that panics: an internal error, and the server lives on.
    let r = c.call("softc/panic", json!({}));
    assert_eq!(r["error"]["code"], -32603, "{r}");
    // A second initialize.
    let r = c.call("initialize", json!({"capabilities": {}}));
    assert_eq!(r["error"]["code"], -32600, "{r}");
    // Notifications with bad params are ignored.
    c.notify("textDocument/didOpen", json!({"textDocument": "nope"}));
    c.notify("textDocument/didChange", json!(42));
    c.notify("$/unknownNotification", json!({}));

    // Odd documents: deep nesting, binary-ish text, a huge one; positions far outside.
    let deep = format!("let a = {}1{}\n", "(".repeat(5000), ")".repeat(5000));
    let odd = "let \u{0}\u{7f} = \"unterminated\nsim { pressure = [[[[ µ 𝑥 \r\n";
    let mut huge = String::new();
    for i in 0..20_000 {
        huge.push_str(&format!("let v{i} = {i} mm + 1 kPa * sqrt(4 mm^2)\n"));
    }
    for (i, text) in [deep.as_str(), odd, huge.as_str()].into_iter().enumerate() {
        let uri = format!("untitled:odd{i}.soft");
        c.open(&uri, text);
        let started = Instant::now();
        let diags = c.diagnostics(&uri);
        assert!(!diags.is_empty(), "odd document {i} has problems");
        eprintln!(
            "odd document {i} ({} bytes): {} diagnostics in {:?}",
            text.len(),
            diags.len(),
            started.elapsed()
        );
        for p in [pos(0, 0), pos(0, 10_000), pos(1_000_000, 3), pos(20_000, 5)] {
            for m in [
                "textDocument/hover",
                "textDocument/definition",
                "textDocument/completion",
                "textDocument/references",
            ] {
                let mut params = json!({"textDocument": {"uri": uri}, "position": p});
                if m == "textDocument/references" {
                    params["context"] = json!({"includeDeclaration": true});
                }
                let r = c.call(m, params);
                assert!(r.get("error").is_none(), "{m} on odd document {i}: {r}");
            }
        }
        let r = c.call(
            "textDocument/documentSymbol",
            json!({"textDocument": {"uri": uri}}),
        );
        assert!(r.get("error").is_none(), "{r}");
        let r = c.call(
            "textDocument/formatting",
            json!({"textDocument": {"uri": uri}, "options": {"tabSize": 2, "insertSpaces": true}}),
        );
        assert!(r.get("error").is_none(), "{r}");
    }

    // Still answering.
    let r = c.call(
        "textDocument/hover",
        json!({"textDocument": {"uri": "untitled:odd2.soft"}, "position": pos(0, 5)}),
    );
    assert!(
        r["result"]["contents"]["value"]
            .as_str()
            .unwrap()
            .contains("let v0"),
        "{r}"
    );
    c.finish();
}

/// Every example gets the same diagnostics from the server as from `softc check`, and the
/// largest is checked quickly enough to type in.
#[test]
fn examples_match_softc_check() {
    let mut c = Client::start();
    c.initialize();
    let mut largest = (0usize, String::new(), Duration::ZERO);
    let mut paths: Vec<PathBuf> = std::fs::read_dir(repo().join("examples"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "soft"))
        .collect();
    paths.sort();
    assert!(paths.len() >= 4);
    for path in paths {
        let text = std::fs::read_to_string(&path).unwrap();
        let uri = file_uri(&path);
        let started = Instant::now();
        c.open(&uri, &text);
        let diags = c.diagnostics(&uri);
        let took = started.elapsed();
        let out = Command::new(env!("CARGO_BIN_EXE_softc"))
            .args(["check", "--message-format", "json"])
            .arg(&path)
            .output()
            .unwrap();
        let expected: Vec<(String, u64)> = String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| {
                let v: Value = serde_json::from_str(l).unwrap();
                (
                    v["code"].as_str().unwrap().to_string(),
                    v["start"]["line"].as_u64().unwrap() - 1,
                )
            })
            .collect();
        let got: Vec<(String, u64)> = diags
            .iter()
            .map(|d| {
                (
                    d["code"].as_str().unwrap().to_string(),
                    d["range"]["start"]["line"].as_u64().unwrap(),
                )
            })
            .collect();
        assert_eq!(got, expected, "{}", path.display());
        if text.len() > largest.0 {
            largest = (text.len(), path.display().to_string(), took);
        }
    }
    eprintln!(
        "diagnostics for the largest example ({}, {} bytes) in {:?}",
        largest.1, largest.0, largest.2
    );
    assert!(largest.2 < Duration::from_secs(10));
    c.finish();
}

#[test]
fn exit_without_shutdown_is_status_1() {
    let mut c = Client::start();
    c.initialize();
    c.notify("exit", Value::Null);
    let deadline = Instant::now() + TIMEOUT;
    loop {
        if let Some(status) = c.child.try_wait().unwrap() {
            assert_eq!(status.code(), Some(1));
            return;
        }
        assert!(Instant::now() < deadline, "softc lsp did not exit");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Issue 31 item 7: functions that each call the previous one twice made the check of a
/// document take minutes (2^n evaluations), wedging the server: it answered nothing else and
/// did not exit when its input closed. Repeated calls are evaluated once, so 30 such levels
/// (10^9 calls unshared) check at once; distinct arguments at every level are E0002 after a
/// bounded number of evaluations.
#[test]
fn a_document_of_exponential_calls_does_not_wedge_the_server() {
    let levels = |distinct: bool| {
        let mut text = String::from("fn f0(a: length) -> length = a\n");
        for i in 1..=30 {
            let second = if distinct { "3 * a + 1 mm" } else { "a" };
            let first = if distinct { "2 * a" } else { "a" };
            text += &format!(
                "fn f{i}(a: length) -> length = f{}({first}) + f{}({second})\n",
                i - 1,
                i - 1
            );
        }
        text + "let reach = f30(1 mm)\n"
    };
    let mut c = Client::start();
    c.initialize();
    let (shared, distinct) = ("file:///shared.soft", "file:///distinct.soft");
    let started = Instant::now();
    c.open(shared, &levels(false));
    c.open(distinct, &levels(true));
    let found = c.diagnostics(shared);
    assert!(found.iter().all(|d| d["code"] != "E0002"), "{found:?}");
    let found = c.diagnostics(distinct);
    assert!(
        found
            .iter()
            .any(|d| d["code"] == "E0002" && d["message"].as_str().unwrap().contains("too complex")),
        "{found:?}"
    );
    // The server still answers, and exits when its input closes.
    let hover = c.result(
        "textDocument/hover",
        json!({"textDocument": {"uri": shared}, "position": pos(30, 5)}),
    );
    assert!(!hover.is_null());
    eprintln!(
        "both documents checked in {:.2} s",
        started.elapsed().as_secs_f64()
    );
    c.close_input();
    let deadline = Instant::now() + TIMEOUT;
    loop {
        if let Some(status) = c.child.try_wait().unwrap() {
            assert_eq!(status.code(), Some(1), "end of input without shutdown");
            return;
        }
        assert!(
            Instant::now() < deadline,
            "softc lsp did not exit when its input closed"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}
