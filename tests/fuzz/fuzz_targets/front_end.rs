//! Feeds arbitrary bytes to the whole front end (decode, parse, check, format). Any panic,
//! stack overflow or timeout is a bug: every input must end in diagnostics.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let options = softc_compiler::sema::CheckOptions::default();
    let (text, checked) = softc_compiler::check_bytes(data, &options);
    let file = softc_compiler::diag::SourceFile::new("fuzz.soft", &text);
    for d in &checked.diagnostics {
        let _ = file.render(d);
        let _ = file.render_json(d);
    }
    if let Ok(t) = std::str::from_utf8(data) {
        if let Ok(formatted) = softc_compiler::fmt::format_source(t) {
            let again = softc_compiler::fmt::format_source(&formatted).expect("formatted output parses");
            assert_eq!(again, formatted);
        }
    }
});
