//! Reading the files a user names (scripts, meshes, mesh specs, `--params`, `state.json`):
//! only regular files, and never more than the size the file had when opened. A FIFO would
//! block the read forever and a device such as `/dev/zero` never ends (issue 20 item 13).

use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// Why `path` is not a regular file, or `None` when it is one (symbolic links are followed).
/// Errors of `stat` itself (not found, no permission) are left to the read that follows.
pub fn not_regular(path: &Path) -> Option<String> {
    let meta = std::fs::metadata(path).ok()?;
    let ty = meta.file_type();
    if ty.is_file() {
        return None;
    }
    Some(if ty.is_dir() {
        "is a folder, not a file".to_string()
    } else {
        format!("is {}, not a regular file", special_kind(&ty))
    })
}

#[cfg(unix)]
fn special_kind(ty: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if ty.is_fifo() {
        "a named pipe (FIFO)"
    } else if ty.is_char_device() {
        "a character device"
    } else if ty.is_block_device() {
        "a block device"
    } else if ty.is_socket() {
        "a socket"
    } else {
        "a special file"
    }
}

#[cfg(not(unix))]
fn special_kind(_: &std::fs::FileType) -> &'static str {
    "a special file"
}

/// Read a regular file whole: anything else is refused before it is opened (an error of kind
/// `InvalidInput` whose message says what the path is), and at most the file's size at
/// opening is read.
pub fn read_regular(path: &Path) -> std::io::Result<Vec<u8>> {
    if let Some(why) = not_regular(path) {
        return Err(Error::new(ErrorKind::InvalidInput, why));
    }
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    // Should the path be swapped for a FIFO between the check and the open, the open must not
    // wait for a writer.
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::fs::OpenOptionsExt;
        const O_NONBLOCK: i32 = 0o4000;
        options.custom_flags(O_NONBLOCK);
    }
    let file = options.open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(Error::new(
            ErrorKind::InvalidInput,
            "is not a regular file (it changed while being opened)",
        ));
    }
    let len = meta.len();
    let mut buf = Vec::with_capacity(usize::try_from(len).unwrap_or(0).min(1 << 30));
    file.take(len).read_to_end(&mut buf)?;
    Ok(buf)
}

/// [`read_regular`] as UTF-8 text.
pub fn read_regular_text(path: &Path) -> std::io::Result<String> {
    let bytes = read_regular(path)?;
    String::from_utf8(bytes).map_err(|_| Error::new(ErrorKind::InvalidData, "is not UTF-8 text"))
}
